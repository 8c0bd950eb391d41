"""A frame turned about z by 90, 180 or 270 degrees (exact on the 0.4 m lattice, the grid being symmetric) must give
the same answer turned: one test for each place where the grid's orientation could enter, and the whole odometry
on frame pairs (relative pose within 1e-6 m after turning back)."""

import numpy as np
import pytest
from scenes import box, town

from occvo_core import OccVO, OccVOConfig
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID
from occvo_core.registration.initialisation import bev_first_motion
from occvo_core.registration.kernels.map_window import ego_points
from occvo_core.registration.kernels.nearest import nearest_in_window, nearest_within
from occvo_core.registration.preprocess import preprocess
from occvo_core.registration.voxel_map import VoxelPFilterMap

TURNS = (90, 180, 270)


def turn(degrees: int) -> np.ndarray:
    """4x4 turn about z, exact (entries 0 and +-1)."""
    c, s = {0: (1, 0), 90: (0, 1), 180: (-1, 0), 270: (0, -1)}[degrees]
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    return out


def turned(points: np.ndarray, degrees: int) -> np.ndarray:
    return np.ascontiguousarray(points @ turn(degrees)[:3, :3].T)


def grid_order(points: np.ndarray, labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points in the order a frame of them has in its own grid (as preprocess sorts it): a turn permutes it."""
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))
    return points[order], labels[order]


def as_set(points: np.ndarray) -> set:
    return set(map(tuple, np.round(points, 6)))


def scene_with_lines():
    """The test town, plus one-voxel lines along x and y (a barrier, a kerb): a line's plane normal is any vector
    across it, which the covariance must choose the same way whichever way the line runs."""
    points, labels = town()
    lines = [box((-20.0, 20.2, 1.0), (-10.0, 20.2, 1.0), 1), box((25.0, -30.0, 1.0), (25.0, -20.0, 1.0), 1)]
    points = np.concatenate([points] + [p for p, _ in lines])
    labels = np.concatenate([labels] + [lab for _, lab in lines])
    _, unique = np.unique(OCC3D_GRID.indices_of(points), axis=0, return_index=True)
    return points[unique], labels[unique]


@pytest.mark.parametrize("degrees", TURNS)
def test_sources_of_a_turned_frame_are_the_same_voxels(degrees):
    """The uniform pick's hash and the blocks (2.4 m wide ones too: 200 voxels are no multiple of 6) turn with the
    frame, so each pass registers the same physical voxels."""
    points, labels = scene_with_lines()
    a = preprocess(OccupancyFrame(*grid_order(points, labels)), OccVOConfig())
    b = preprocess(OccupancyFrame(*grid_order(turned(points, degrees), labels)), OccVOConfig())
    back = turn(degrees).T
    for name in ("wide", "coarse", "fine"):
        picked_a = a.points[getattr(a, name)]
        picked_b = b.points[getattr(b, name)] @ back[:3, :3].T
        assert as_set(picked_a) == as_set(picked_b), name


@pytest.mark.parametrize("degrees", TURNS)
def test_covariances_of_a_turned_frame_are_the_covariances_turned(degrees):
    points, labels = scene_with_lines()
    a = preprocess(OccupancyFrame(*grid_order(points, labels)), OccVOConfig())
    b = preprocess(OccupancyFrame(*grid_order(turned(points, degrees), labels)), OccVOConfig())
    rot = turn(degrees)[:3, :3]
    back = b.points @ rot
    order_a, order_b = np.lexsort(np.round(a.points, 6).T), np.lexsort(np.round(back, 6).T)
    assert np.allclose(a.points[order_a], back[order_b], atol=1e-9)
    covs_back = np.einsum("ji,njk,kl->nil", rot, b.covs, rot)
    assert np.abs(a.covs[order_a] - covs_back[order_b]).max() < 1e-12
    # a line of voxels has no plane (a normal picked across it would turn with the axes, and z lies along a pole):
    # 1 along the line, eps across it every way, on the one-voxel lines and inside the town's poles (2 x 2 columns)
    eps = OccVOConfig().gicp.covariance_epsilon
    on_line = np.flatnonzero(np.isclose(a.points[:, 2], 1.2, atol=0.01) & (a.labels == 1))
    assert len(on_line) > 40
    along = np.where(np.isclose(a.covs[on_line, 0, 0], 1.0)[:, None], [1.0, eps, eps], [eps, 1.0, eps])
    inner = np.abs(a.covs[on_line] - along[:, :, None] * np.eye(3)).max(axis=(1, 2)) < 1e-12
    # at the lines' four ends a radius-1 neighbourhood holds two voxels, too few (isotropic); a wider one the line
    ends = 4 if OccVOConfig().gicp.k_neighbours_radius_voxels == 1 else 0
    assert inner.sum() == len(on_line) - ends
    pole = np.flatnonzero(
        np.isin(np.round(a.points[:, 0], 3), (9.0, 9.4)) & np.isin(np.round(a.points[:, 1], 3), (7.0, 7.4))
    )
    inside = pole[(a.points[pole, 2] > 0.0) & (a.points[pole, 2] < 3.0)]
    assert len(inside) >= 20
    assert np.abs(a.covs[inside] - np.diag([eps, eps, 1.0])).max() < 1e-12


def _tie_map(voxel: float):
    """A map with two points at exactly the same distance from a query (coordinates in halves: no rounding), the
    query off the centre so that the two are not turned copies of each other about the origin."""
    q = np.array([6.25, 3.25, 0.25])
    pts = np.array([q + [voxel, 0, 0], q + [0, voxel, 0], q + [0, 0, 3 * voxel]])
    return q, pts


@pytest.mark.parametrize("search", ["in_window", "within"])
def test_nearest_neighbour_tie_is_the_same_point_after_a_turn(search):
    """Rings are read in axis order, which a turn permutes: a tie must go by an order a turn keeps."""
    voxel = 0.5
    q, pts = _tie_map(voxel)
    chosen = []
    for degrees in (0, *TURNS):
        m = VoxelPFilterMap(voxel, merge_radius_m=0.0)
        p = turned(pts, degrees)
        order = np.lexsort((p[:, 2], p[:, 1], p[:, 0]))  # rows in the turned grid's order, as a real map has them
        m.merge(p[order], np.zeros(len(p), np.uint8), np.tile(np.eye(3), (len(p), 1, 1)), 0)
        local = m.window(np.array([-40, -40, -10]), np.array([40, 40, 10]))
        query = turned(q[None], degrees)[0]
        if search == "in_window":
            best, d2 = nearest_in_window(query, local.pos, local.grid, local.origin, local.dims, voxel, 2, local.usable)
        else:
            best, d2 = nearest_within(
                query, local.pos, local.grid, local.origin, local.dims, voxel, 2, local.usable, 4 * voxel**2
            )
        assert d2 == pytest.approx(voxel**2)
        chosen.append(tuple(np.round(turned(local.pos[best][None], (360 - degrees) % 360)[0], 9)))
    assert len(set(chosen)) == 1, chosen


def test_two_map_voxels_in_one_ego_cell_keep_the_same_one_after_a_turn():
    """A yawed pose puts two map voxels in one cell of the ego grid; the one kept must not be the later row (rows
    come in the turned frame's grid order)."""
    pts = np.array([[4.85, 2.85, 0.05], [5.1, 3.1, 0.3], [-7.1, 2.2, 0.1]])
    kept = []
    for degrees in (0, *TURNS):
        p = turned(pts, degrees)
        p = p[np.lexsort((p[:, 2], p[:, 1], p[:, 0]))]
        covs = np.tile(np.eye(3), (len(p), 1, 1))
        origin, dims = np.array([-30, -30, -5]), np.array([60, 60, 10])
        pos, _, grid = ego_points(
            np.arange(len(p)), np.arange(len(p)), p, covs, np.eye(3), np.zeros(3), origin, dims, 0.4, 2
        )
        winners = pos[grid[grid >= 0]]
        kept.append(as_set(turned(winners, (360 - degrees) % 360)))
    assert len(kept[0]) == 2  # the first two share a cell
    assert all(k == kept[0] for k in kept)


def test_new_voxels_do_not_depend_on_the_frames_point_order():
    """Two points of a frame in one empty map cell, one near an old voxel and one not: the map they make must not
    depend on which comes first (a turn reorders a frame's points)."""
    old = np.array([[1.1, 1.1, 0.1]])
    near_old, far = [1.22, 1.25, 0.1], [1.55, 1.55, 0.35]  # both in cell (3, 3, 0); only the first within 0.2 m
    maps = []
    for frame in ([near_old, far], [far, near_old]):
        m = VoxelPFilterMap(0.4, merge_radius_m=0.2)
        m.merge(old, np.zeros(1, np.uint8), np.eye(3)[None], 0)
        m.merge(np.array(frame), np.zeros(2, np.uint8), np.tile(np.eye(3), (2, 1, 1)), 1)
        points = m.pos[: m._n]
        maps.append(points[np.lexsort(points.T)])
    assert len(maps[0]) == 2  # the old voxel and one new one holding both points
    assert np.array_equal(maps[0], maps[1])


@pytest.mark.parametrize("degrees", TURNS)
def test_first_motion_search_of_a_turned_pair_is_the_motion_turned(degrees):
    points, labels = town()
    motion = np.eye(4)
    motion[:3, 3] = [1.6, 0.8, 0.0]
    second = (points - motion[:3, 3])[OCC3D_GRID.inside(OCC3D_GRID.indices_of(points - motion[:3, 3]))]
    second_labels = labels[OCC3D_GRID.inside(OCC3D_GRID.indices_of(points - motion[:3, 3]))]
    kw = {"search_radius_m": 12.0, "yaw_steps_deg": (-6.0, -3.0, 0.0, 3.0, 6.0)}
    a, _ = bev_first_motion(points, labels, second, second_labels, **kw)
    b, _ = bev_first_motion(turned(points, degrees), labels, turned(second, degrees), second_labels, **kw)
    assert np.allclose(a, turn(degrees).T @ b @ turn(degrees), atol=1e-9)


def _pair_motion(frames: list[OccupancyFrame], degrees: int) -> np.ndarray:
    """Relative pose of the second frame to the first, both turned, turned back."""
    vo = OccVO(OccVOConfig(), threads=1)
    for f in frames:
        p, lab = grid_order(turned(f.points, degrees), f.labels)
        vo.step(OccupancyFrame(p, lab, f.index))
    rel = np.linalg.inv(vo.poses[0]) @ vo.poses[1]
    return turn(degrees).T @ rel @ turn(degrees)


def _assert_same_relative_pose(frames):
    plain = _pair_motion(frames, 0)
    for degrees in TURNS:
        other = _pair_motion(frames, degrees)
        assert np.linalg.norm(other[:3, 3] - plain[:3, 3]) < 1e-6, degrees
        assert np.abs(other[:3, :3] - plain[:3, :3]).max() < 1e-9, degrees


@pytest.mark.parametrize("start", [10, 20])
def test_real_frame_pair_turned_gives_the_same_relative_pose(scene_0101, start):
    """Real occupancy (nuScenes scene-0101): sources, covariances, first-motion search, ego grid, nearest pairs,
    GICP's sums and stopping all together."""
    _assert_same_relative_pose([scene_0101[start], scene_0101[start + 1]])


def test_synthetic_frame_pair_turned_gives_the_same_relative_pose():
    from occvo_core.sim import SyntheticScene

    scene = SyntheticScene(seed=3, frames=8)
    _assert_same_relative_pose([scene[5], scene[6]])


@pytest.mark.parametrize("margin_m", [0.0, 3.3, 4.0])
def test_ego_grid_and_its_pooled_grids_are_symmetric_about_the_ego(margin_m):
    """The ego map's box and the coarse and wide pooled boxes must reach as far to -x as to +x (and in y): a cell
    more on one side holds map a turned frame does not see."""
    from occvo_core.registration.local_map import EGO_LOWER, EGO_UPPER, _coarser_box, _ego_box, window_margin

    margin = window_margin(margin_m)
    origin, dims = _ego_box(EGO_LOWER - margin, EGO_UPPER + margin, 0.4)
    boxes = [(origin, dims, 0.4)]
    for coarse in (1.2, 2.4):
        boxes.append((*_coarser_box(*boxes[-1], coarse), coarse))
    for o, d, voxel in boxes:
        assert np.array_equal(o[:2], -(o[:2] + d[:2])), (voxel, o, d)
        assert o[0] * voxel <= EGO_LOWER[0] - margin[0] + 1e-9


def test_two_corrected_voxels_in_one_cell_keep_the_same_one_whatever_their_rows():
    """A loop closure moves voxels; two landing in one cell keep one, which must not be the earlier row (rows come
    in the order the frames were turned in)."""
    pts = np.array([[4.85, 2.85, 0.05], [5.1, 3.1, 0.3], [-7.1, 2.2, 0.1]])  # after the correction
    drift = np.array([[0.8, 0.0, 0.0], [0.0, 0.8, 0.0], [0.0, 0.0, 0.0]])  # before it, in three cells
    kept = []
    for degrees in (0, *TURNS):
        for order in ([0, 1, 2], [1, 0, 2]):
            m = VoxelPFilterMap(0.4, merge_radius_m=0.0)
            m.merge(turned(pts[order] + drift[order], degrees), np.zeros(3, np.uint8), np.tile(np.eye(3), (3, 1, 1)), 0)
            assert len(m) == 3
            m.move(np.arange(3), np.tile(np.eye(3), (3, 1, 1)), turned(-drift[order], degrees))
            alive = m.pos[: m._n][m.alive[: m._n]]
            kept.append(as_set(turned(alive, (360 - degrees) % 360)))
    assert len(kept[0]) == 2  # the first two share a cell after the correction
    assert all(k == kept[0] for k in kept)
