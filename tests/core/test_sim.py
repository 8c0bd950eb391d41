"""The procedural town: determinism, visibility, noise rates, ground truth, scene contents."""

import hashlib

import numpy as np
import pytest

from occvo_core.datasets.base import SceneSource
from occvo_core.errors import ConfigError
from occvo_core.grid import FREE, MOVABLE_CLASSES, OCC3D_GRID, STATIC_CLASSES
from occvo_core.sim import CAMERAS, NoiseModel, SyntheticScene, render
from occvo_core.sim.noise import false_positive_candidates


def _digest(scene, n):
    h = hashlib.sha256(scene.gt_poses.tobytes())
    for i in range(n):
        f = scene[i]
        h.update(f.points.tobytes())
        h.update(f.labels.tobytes())
    return h.hexdigest()


@pytest.fixture(scope="module")
def scene():
    return SyntheticScene(seed=3, frames=12)


def test_same_seed_gives_identical_bytes():
    a, b = SyntheticScene(seed=5, frames=6), SyntheticScene(seed=5, frames=6)
    assert _digest(a, 6) == _digest(b, 6)
    assert np.array_equal(a.true_grid(4), b.true_grid(4))
    assert _digest(SyntheticScene(seed=6, frames=6), 6) != _digest(a, 6)


def test_frame_does_not_depend_on_access_order():
    a, b = SyntheticScene(seed=2, frames=5), SyntheticScene(seed=2, frames=5)
    late_first = b[4]
    [a[i] for i in range(5)]
    assert np.array_equal(a[4].points, late_first.points) and np.array_equal(a[4].labels, late_first.labels)


def test_scene_source_protocol_and_frames(scene):
    assert isinstance(scene, SceneSource)
    assert len(scene) == 12 and scene.rate_hz == 2.0 and scene.name == "synthetic-0003"
    f = scene[3].validate()
    assert f.index == 3 and f.stamp == pytest.approx(1.5)
    assert f.points.dtype == np.float64 and f.labels.dtype == np.uint8
    idx = OCC3D_GRID.indices_of(f.points)
    assert OCC3D_GRID.inside(idx).all()
    assert np.allclose(OCC3D_GRID.centres_of(idx), f.points)  # voxel centres
    assert scene.gt_poses.shape == (12, 4, 4)
    assert np.allclose(scene.gt_poses[:, :3, :3] @ scene.gt_poses[:, :3, :3].transpose(0, 2, 1), np.eye(3), atol=1e-9)
    with pytest.raises(IndexError):
        scene[12]


def test_bad_arguments_are_config_errors():
    with pytest.raises(ConfigError):
        SyntheticScene(frames=0)
    with pytest.raises(ConfigError):
        SyntheticScene(noise="loud")
    with pytest.raises(ConfigError):
        SyntheticScene(seed=-1)


def test_town_has_the_occ3d_classes_a_street_shows(scene):
    seen = np.zeros(18, int)
    for i in range(0, 12, 3):
        seen += np.bincount(scene.true_grid(i)[scene.camera_mask(i)], minlength=18)
    for cls in (11, 13, 14, 15, 16):  # road, sidewalk, terrain, manmade, vegetation
        assert seen[cls] > 200, cls
    assert seen[1] + seen[8] > 0  # barriers or cones
    assert seen[[c for c in MOVABLE_CLASSES]].sum() > 50  # vehicles / pedestrians


def test_ego_drive_has_a_stop_turns_and_speed_limits():
    s = SyntheticScene(seed=0)
    speeds = s.speeds
    assert speeds.max() <= 15.0 and speeds.min() >= 0.0
    assert (speeds < 0.05).sum() >= 2  # stands still at the first intersection
    yaw = np.unwrap(np.arctan2(s.gt_poses[:, 1, 0], s.gt_poses[:, 0, 0]))
    assert abs(yaw[-1] - yaw[0]) > np.radians(45) or np.abs(np.diff(yaw)).sum() > np.radians(60)


def test_visibility_hides_voxels_behind_a_wall():
    grid = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    grid[:, :, 1] = 11  # ground slab
    grid[:, :, 2] = 11
    # a 3.2 m high wall 10 m ahead, spanning y in [-8, 8]
    wx = int((10.0 + 40) / 0.4)
    grid[wx : wx + 2, 80:120, 3:11] = 15
    # a car-sized box 5 m behind the wall and a pole far behind it
    grid[wx + 12 : wx + 20, 95:100, 3:7] = 4
    grid[wx + 40, 100, 3:15] = 15
    mask = np.zeros(grid.shape, bool)
    render.visibility(grid != FREE, CAMERAS, render.LOWER, render.VOXEL, 0.007, mask)
    assert mask[wx, 100, 5] and mask[wx, 90, 4]  # the wall's face is observed
    assert not mask[wx + 1, 100, 5]  # its back layer is not
    assert not mask[wx + 12 : wx + 20, 95:100, 3:7].any()  # the box behind it is not
    assert not mask[wx + 40, 100, 3:9].any()  # nor the pole, below the wall's shadow line
    assert mask[100 - 30, 100, 2]  # ground 12 m behind the ego (back camera) is
    assert not mask[100, 100, 1]  # ground under the ego is outside every camera's view


def test_visibility_in_scenes_emits_only_observed_voxels(scene):
    full, mask = scene.true_grid(5), scene.camera_mask(5)
    clean = SyntheticScene(seed=3, frames=12, noise="none")[5]
    idx = OCC3D_GRID.indices_of(clean.points)
    assert mask[idx[:, 0], idx[:, 1], idx[:, 2]].all()
    assert len(clean) == int(((full != FREE) & mask).sum())
    assert len(clean) < int((full != FREE).sum()) / 2  # most of the world is hidden


def _noise_counts(model, seed=0):
    s = SyntheticScene(seed=1, frames=1, noise="none", traffic=True)
    truth, mask = s.true_grid(0), s.camera_mask(0)
    out = model.apply(truth, mask, np.random.default_rng(seed))
    return truth, mask, out


def test_noise_drop_and_confusion_rates_match_knobs():
    truth, mask, out = _noise_counts(NoiseModel(drop_rate=0.2, confusion_rate=0.1))
    vis = (truth != FREE) & mask
    n = int(vis.sum())
    dropped = (out[vis] == FREE).mean()
    kept = vis & (out != FREE)
    confused = (out[kept] != truth[kept]).mean()
    tol = lambda p, n: 4 * np.sqrt(p * (1 - p) / n)  # noqa: E731
    assert abs(dropped - 0.2) < tol(0.2, n)
    assert abs(confused - 0.1) < tol(0.1, kept.sum()) + 0.01  # voxels of classes without neighbours cannot change
    assert not (out[~mask] != FREE).any()


def test_noise_false_positive_rate_matches_knob():
    truth, mask, out = _noise_counts(NoiseModel(false_positive_rate=0.05))
    cand = false_positive_candidates((truth != FREE) & mask, mask)
    turned = out[cand[:, 0], cand[:, 1], cand[:, 2]] != FREE
    assert abs(turned.mean() - 0.05) < 4 * np.sqrt(0.05 * 0.95 / len(cand))
    vis = (truth != FREE) & mask
    assert np.array_equal(out[vis], truth[vis])  # only additions
    assert (out != FREE).sum() == vis.sum() + turned.sum()


def test_noise_grows_with_distance_and_jitter_moves_thin_columns():
    truth, mask, out = _noise_counts(NoiseModel(drop_rate=0.1, distance_gain=2.0))
    vis = (truth != FREE) & mask
    c = OCC3D_GRID.centres_of(np.argwhere(vis))
    r = np.hypot(c[:, 0], c[:, 1])
    dropped = out[vis] == FREE
    near, far = dropped[r < 10].mean(), dropped[r > 30].mean()
    assert near < 0.16 and far > 0.22 and far > 1.5 * near
    truth, mask, out = _noise_counts(NoiseModel(jitter_rate=1.0))
    vis = (truth != FREE) & mask
    assert (out != FREE).sum() <= vis.sum()
    assert 0 < (vis & (out == FREE)).sum() < 0.2 * vis.sum()  # thin structures only


def test_persistent_errors_repeat_at_the_same_world_place():
    model = NoiseModel(drop_rate=0.3, persistence=1.0, patch_m=1.6)
    s = SyntheticScene(seed=1, frames=1, noise="none")
    truth, mask, pose = s.true_grid(0), s.camera_mask(0), s.gt_poses[0]
    a = model.apply(truth, mask, np.random.default_rng(1), pose, seed=1)
    b = model.apply(truth, mask, np.random.default_rng(2), pose, seed=1)
    assert np.array_equal(a, b)
    assert NoiseModel.preset("default").persistence > 0.5
    with pytest.raises(ValueError):
        NoiseModel.preset("nope")


def test_static_map_and_dynamic_tracks(scene):
    points, labels = scene.static_map()
    assert points.shape[1] == 3 and len(points) == len(labels) > 10000
    assert np.isin(labels, STATIC_CLASSES).mean() > 0.9
    keys = np.floor(points / 0.4).astype(np.int64)
    assert len(np.unique(keys, axis=0)) == len(points)
    # the clean frame, moved to the world, lies on the static map except for moving agents
    clean = SyntheticScene(seed=3, frames=12, noise="none")
    f, pose = clean[6], clean.gt_poses[6]
    static = np.isin(f.labels, STATIC_CLASSES)
    world = f.points[static] @ pose[:3, :3].T + pose[:3, 3]
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(world)
    assert (d < 0.4).mean() > 0.99
    tracks = scene.dynamic_tracks()
    assert tracks and all(t.poses.shape == (12, 4, 4) for t in tracks)
    assert any(np.linalg.norm(t.poses[-1, :3, 3] - t.poses[0, :3, 3]) > 5 for t in tracks)
    assert any(t.label == 7 for t in tracks)


def test_traffic_off_has_no_moving_agents():
    s = SyntheticScene(seed=4, frames=3, traffic=False)
    assert s.dynamic_tracks() == []
    assert np.array_equal(s.true_grid(2), SyntheticScene(seed=4, frames=3, traffic=False).true_grid(2))


def test_world_stays_small():
    s = SyntheticScene(seed=0)
    assert s.town.nbytes() < 40e6


def test_persistent_draws_keep_the_knob_rates():
    s = SyntheticScene(seed=1, frames=1, noise="none")
    truth, mask, pose = s.true_grid(0), s.camera_mask(0), s.gt_poses[0]
    out = NoiseModel(drop_rate=0.2, persistence=0.97).apply(truth, mask, np.random.default_rng(0), pose, seed=1)
    vis = (truth != FREE) & mask
    assert abs((out[vis] == FREE).mean() - 0.2) < 0.04  # patches are correlated: wider tolerance
