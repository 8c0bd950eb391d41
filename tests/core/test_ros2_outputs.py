"""What fusion stacks read from occvo's recordings: odom -> base_link never jumps when a loop closes (map -> odom
takes the correction), the twist is the motion between frames, and a bag grows linearly with the drive (a bounded
path window, the map near the ego)."""

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.frame import OccupancyFrame
from occvo_core.viz.odom_frames import OdomFrames


def _pose(x, yaw=0.0):
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0, x], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])


def test_a_loop_closure_moves_map_to_odom_and_never_odom_to_base_link():
    frames = OdomFrames()
    cov = np.diag([1e-4, 1e-4, 1e-4, 4e-4, 1e-4, 1e-5])  # rotation, translation in base_link
    correction = _pose(-0.5, 0.01)  # world -> world: the loop pulls the poses back half a metre
    odoms = []
    for i in range(6):
        raw = _pose(2.0 * i)  # as registered before the loop
        pose = correction @ raw if i >= 3 else raw  # from frame 3 on, relocalised
        odoms.append(frames.update(pose, i * 500_000_000, cov, correction if i == 3 else None)[0])
        if i >= 3:
            np.testing.assert_allclose(frames.map_to_odom, correction)
    steps = np.diff([o[0, 3] for o in odoms])
    np.testing.assert_allclose(steps, 2.0, atol=1e-12)  # odom moves as the car did, the jump is in map -> odom


def _perturbed(pose, cov, rng, n):
    """n poses pose @ exp(eps), eps ~ N(0, cov) in base_link (rotation, translation)."""
    eps = rng.multivariate_normal(np.zeros(6), cov, n)
    out = np.tile(np.eye(4), (n, 1, 1))
    out[:, :3, :3] = Rotation.from_rotvec(eps[:, :3]).as_matrix()
    out[:, :3, 3] = eps[:, 3:]  # first order: the translation as it is
    return pose @ out


def test_the_twist_is_the_motion_between_frames_and_its_covariance_both_frames_errors():
    before, after = _pose(0.3, 0.2), _pose(1.3, 0.3)
    cov_before = np.diag([1e-4, 2e-4, 3e-4, 4e-4, 5e-4, 6e-4])
    cov_after = np.diag([3e-4, 1e-4, 2e-4, 6e-4, 4e-4, 5e-4])
    frames = OdomFrames()
    frames.update(before, 0, cov_before)
    odom, pose_cov, (linear, angular), twist_cov = frames.update(after, 500_000_000, cov_after)
    rel = np.linalg.inv(before) @ after
    np.testing.assert_allclose(linear, rel[:3, :3].T @ rel[:3, 3] / 0.5, atol=1e-12)  # in base_link now
    np.testing.assert_allclose(angular, [0, 0, 0.2], atol=1e-12)
    assert np.isclose(pose_cov[2, 2], 5e-4) and np.isclose(pose_cov[0, 0] + pose_cov[1, 1], 1e-3)
    rng = np.random.default_rng(1)  # the covariance as sampled: both poses perturbed, the twist recomputed
    a, b = _perturbed(before, cov_before, rng, 20000), _perturbed(after, cov_after, rng, 20000)
    rels = np.linalg.inv(a) @ b
    lin = np.einsum("nji,nj->ni", rels[:, :3, :3], rels[:, :3, 3]) / 0.5
    ang = Rotation.from_matrix(rels[:, :3, :3]).as_rotvec() / 0.5
    sampled = np.cov(np.hstack([lin, ang]).T)
    np.testing.assert_allclose(twist_cov, sampled, rtol=0.1, atol=2e-4)
    np.testing.assert_allclose(pose_cov, pose_cov.T)


class _Street:
    """A straight street of fixed voxels: each frame sees those within 40 m of the car (its grid's reach), and the
    map holds every voxel seen so far, so the whole map grows with the drive as a real one does."""

    def __init__(self, length_m: float):
        rng = np.random.default_rng(0)
        n = int(25 * (length_m + 100))  # about 2,000 voxels in a frame's 80 m
        self.world = (np.floor(rng.uniform([-50, -40, -1], [length_m + 50, 40, 5], (n, 3)) / 0.4) + 0.5) * 0.4
        self.seen_to = -np.inf

    def frame(self, x: float) -> np.ndarray:
        self.seen_to = x + 40
        near = np.abs(self.world[:, 0] - x) <= 40
        return self.world[near] - [x, 0, 0]

    def map_points(self, tiles=None):
        p = self.world[self.world[:, 0] <= self.seen_to]
        if tiles is not None:
            lo, hi, tile = tiles
            cell = np.floor(p[:, :2] / tile)
            p = p[np.all((cell >= lo) & (cell <= hi), axis=1)]
        return p, np.full(len(p), 11, np.uint8)


def _bytes_per_frame(path, frames: int) -> float:
    from occvo_core.viz.ros2_bag import Ros2Bag

    bag, street = Ros2Bag(path), _Street(2.5 * frames)
    for i in range(frames):
        pose = _pose(2.5 * i)
        points = street.frame(2.5 * i)
        frame = OccupancyFrame(points, np.full(len(points), 11, np.uint8), i, 1.5e9 + i * 0.5)
        result = type("Step", (), {"pose": pose, "covariance": np.eye(6) * 1e-4, "loop_correction": None})()
        bag.step(frame, result, street)
    bag.finish(street)
    return sum(f.stat().st_size for f in path.iterdir()) / frames


def test_the_bag_grows_linearly_with_the_drive(tmp_path):
    short, long = _bytes_per_frame(tmp_path / "short", 40), _bytes_per_frame(tmp_path / "long", 400)
    assert long < 1.2 * short, (short, long)  # the whole map every 5 frames: 1.8x; the whole path every frame: 1.25x
