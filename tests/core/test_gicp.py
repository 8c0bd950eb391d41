import numpy as np
import pytest
from conftest import random_pose
from scenes import town

from occvo_core.grid import OCC3D_GRID
from occvo_core.registration.gicp import gicp
from occvo_core.registration.kernels.covariance import _smallest_eigenvector, plane_covariances
from occvo_core.registration.kernels.gicp import gicp_linearise_pairs
from occvo_core.registration.kernels.gicp_loop import gicp_linearise
from occvo_core.registration.kernels.grid import surface_voxels
from occvo_core.registration.kernels.nearest import nearest_within
from occvo_core.registration.kernels.sources import thin_sources
from occvo_core.registration.voxel_map import VoxelPFilterMap


def _surface_town():
    points, labels = town()
    ijk = OCC3D_GRID.indices_of(points)
    keep = surface_voxels(ijk, np.array(OCC3D_GRID.shape))
    return points[keep], labels[keep]


def _prepared(points):
    ijk = OCC3D_GRID.indices_of(points)
    shape = np.array(OCC3D_GRID.shape, np.int64)
    return plane_covariances(ijk, shape, 1, 1e-3)


def _map_at(pose, points, labels, covs):
    m = VoxelPFilterMap()
    rot = pose[:3, :3]
    m.merge(points @ rot.T + pose[:3, 3], labels, np.einsum("ij,njk,lk->nil", rot, covs, rot), 0)
    lower = np.floor(pose[:3, 3] / 0.4).astype(int) - 150
    return m.window(lower, lower + 300, 1)


@pytest.mark.parametrize("reuse", [0.0, 0.25])
@pytest.mark.parametrize("seed", range(4))
def test_gicp_recovers_known_rigid_transform(seed, reuse):
    rng = np.random.default_rng(seed)
    points, labels = _surface_town()
    covs = _prepared(points)
    truth = random_pose(rng, np.deg2rad(3), 0.6)
    local = _map_at(truth, points, labels, covs)
    result = gicp(
        points,
        covs,
        labels,
        local,
        np.eye(4),
        max_correspondence_m=1.2,
        iterations=40,
        semantic_label_filter=True,
        correspondence_reuse=reuse,
    )
    err = np.linalg.inv(truth) @ result.pose
    assert np.linalg.norm(err[:3, 3]) < 0.01
    assert np.degrees(np.arccos(np.clip((np.trace(err[:3, :3]) - 1) / 2, -1, 1))) < 0.05
    assert result.pairs_kept > 0.9 * len(points)


def test_plane_covariance_is_flat_along_the_surface_normal():
    points, _ = town()
    covs = _prepared(points)
    ground = np.flatnonzero(np.isclose(points[:, 2], -0.8) & (np.abs(points[:, 0]) < 5) & (np.abs(points[:, 1]) < 5))
    for c in covs[ground[:20]]:
        w, v = np.linalg.eigh(c)
        assert np.allclose(w, [1e-3, 1, 1], atol=1e-6)
        assert abs(abs(v[2, 0]) - 1) < 1e-6  # the flat direction is z, the ground's normal


@pytest.mark.parametrize("radius", [1, 2, 3])
def test_plane_covariances_read_every_neighbour_of_the_cube(radius):
    """The neighbourhood is read a column at a time from occupancy bits: each covariance must be the plane of the
    voxels within `radius` of it every way, counted one by one, also at the grid's floor, top and sides."""
    rng = np.random.default_rng(radius)
    shape = np.array(OCC3D_GRID.shape, np.int64)
    ijk = np.unique(rng.integers(0, [12, 12, shape[2]], size=(900, 3)), axis=0)
    ijk[:, :2] += [0, shape[1] - 12]  # a corner of the grid: its sides cut neighbourhoods off
    eps = 0.05
    covs = plane_covariances(ijk, shape, radius, eps)
    checked = 0
    for n in range(len(ijk)):
        near = ijk[np.abs(ijk - ijk[n]).max(axis=1) <= radius] - ijk[n]
        w, v = np.linalg.eigh(np.cov(near.T.astype(float), bias=True))
        if len(near) < 3 or w[1] - w[0] < 1e-6 * w[2]:
            continue  # no single normal: lines and lone voxels are covered by test_orientation
        assert np.allclose(covs[n], np.eye(3) + (eps - 1) * np.outer(v[:, 0], v[:, 0]), atol=1e-9)
        checked += 1
    assert checked > 0.9 * len(ijk)


def test_smallest_eigenvector_matches_numpy():
    rng = np.random.default_rng(0)
    for _ in range(200):
        a = rng.normal(size=(3, 3))
        a = a @ a.T
        *n, plane = _smallest_eigenvector(a[0, 0], a[0, 1], a[0, 2], a[1, 1], a[1, 2], a[2, 2])
        w, v = np.linalg.eigh(a)
        assert plane and abs(abs(np.array(n) @ v[:, 0]) - 1) < 1e-6
    # two equal smallest eigenvalues (a line of voxels along (1, 1, 0)): no plane
    line = np.array([[2.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 1.0]])
    assert not _smallest_eigenvector(*line[0], *line[1, 1:], line[2, 2])[3]


def test_nearest_in_window_is_the_true_nearest_within_radius():
    rng = np.random.default_rng(1)
    m = VoxelPFilterMap()
    pts = rng.uniform(-10, 10, (3000, 3))
    m.merge(pts, np.zeros(len(pts), np.uint8), np.tile(np.eye(3), (len(pts), 1, 1)), 0)
    local = m.window(np.array([-30, -30, -30]), np.array([30, 30, 30]))
    queries = rng.uniform(-9, 9, (500, 3))
    dist, idx = local.nearest(queries, 3)
    brute = np.linalg.norm(queries[:, None] - local.pos[None], axis=2)
    best = brute.min(axis=1)
    within = best <= 3 * 0.4
    assert np.allclose(dist[within], best[within])


@pytest.mark.parametrize("voxel, radius, max_d", [(0.4, 2, 0.6), (1.2, 1, 1.2)])  # fine GICP's, coarse GICP's
def test_nearest_within_finds_the_true_nearest_whenever_it_is_within_the_limit(voxel, radius, max_d):
    """Beyond its own cell the search reads only cells that can hold a nearer point within the limit: the answer
    must still be the brute-force nearest of the grid's points, on queries inside the padded box and at its edges."""
    rng = np.random.default_rng(3)
    pad, s = radius, voxel / 0.4
    pts = np.concatenate([rng.uniform(-3, 3, (1500, 3)), rng.normal(0, 0.3, (300, 3))]) * s
    usable = rng.random(len(pts)) < 0.9
    cells = np.floor(pts / voxel).astype(np.int64)
    origin = cells.min(axis=0) - pad
    dims = cells.max(axis=0) - origin + 1 + pad
    grid = np.full(int(np.prod(dims)), -1, np.int64)
    for n, (i, j, k) in enumerate(cells - origin):  # a later point in the same cell wins, as on an EgoMap
        grid[(i * dims[1] + j) * dims[2] + k] = n
    held = np.flatnonzero(np.isin(np.arange(len(pts)), grid) & usable)
    queries = np.concatenate([rng.uniform(-3.5, 3.5, (3000, 3)), rng.normal(0, 0.3, (500, 3))]) * s
    close = 0
    for q in queries:
        m, d2 = nearest_within(q, pts, grid, origin, dims, voxel, radius, usable, max_d**2)
        d = np.linalg.norm(pts[held] - q, axis=1)
        if d.min() <= max_d:
            close += 1
            assert m == held[d.argmin()] and np.isclose(d2, d.min() ** 2, rtol=1e-12, atol=0)
        else:
            assert m < 0 or d2 > max_d**2
    assert close > 2000  # most queries have a point to find


def test_kept_pairs_linearise_as_a_fresh_search_does():
    """gicp_linearise_pairs with the pairs a search just found gives that search's H, g and cost."""
    points, labels = _surface_town()
    covs = _prepared(points)
    local = _map_at(random_pose(np.random.default_rng(7), np.deg2rad(2), 0.3), points, labels, covs)
    rot, trans = np.eye(3), np.zeros(3)
    pairs = np.empty(len(points), np.int64)
    h, g, cost, found, kept = gicp_linearise(
        points,
        covs,
        labels.astype(np.int64),
        rot,
        trans,
        local.pos,
        local.cov,
        local.labels.astype(np.int64),
        local.usable,
        local.grid,
        local.origin,
        local.dims,
        local.voxel,
        2,
        0.8,
        True,
        0.0,
        pairs,
    )
    h2, g2, cost2, _, kept2 = gicp_linearise_pairs(points, covs, rot, trans, local.pos, local.cov, pairs, 0.0)
    assert kept == kept2 == int((pairs >= 0).sum()) and 0 < kept <= found
    assert np.allclose(h, h2, rtol=1e-12, atol=0) and np.allclose(g, g2, rtol=1e-12, atol=0) and np.isclose(cost, cost2)


def test_source_pick_first_takes_each_blocks_rear_most_voxel_and_balanced_the_front_most_in_odd_blocks():
    """Two full 2x2x2 blocks along x, in grid order: block (0,0,0) has even parity, block (1,0,0) odd. 'first'
    leans every pick to the rear (lowest x)."""
    shape = np.array(OCC3D_GRID.shape)
    ijk = np.array([(i, j, k) for i in range(4) for j in range(2) for k in range(2)], np.int64)
    off_ground = np.zeros(len(ijk), bool)
    _, _, first = thin_sources(ijk, off_ground, shape, 0, 0, 2, 4, 0)
    _, _, balanced = thin_sources(ijk, off_ground, shape, 0, 0, 2, 4, 1)
    assert ijk[first].tolist() == [[0, 0, 0], [2, 0, 0]]
    assert ijk[balanced].tolist() == [[0, 0, 0], [3, 1, 1]]
    # the ground's own block size: one block of 4, even parity, so its first voxel either way
    on_ground = np.ones(len(ijk), bool)
    assert thin_sources(ijk, on_ground, shape, 0, 0, 2, 4, 1)[2].tolist() == [0]


def test_uniform_source_pick_leans_no_way_and_does_not_depend_on_point_order():
    """Every cell of a full 40x40x8 box: 'uniform' picks one voxel a 2x2x2 block, each of the block's eight
    positions about as often, so the picks' mean offset from their blocks' centres is near zero on every axis
    (where 'first' is half a voxel back on all three)."""
    shape = np.array(OCC3D_GRID.shape)
    ijk = np.array([(i, j, k) for i in range(40) for j in range(40) for k in range(8)], np.int64)
    off_ground = np.zeros(len(ijk), bool)
    _, _, uniform = thin_sources(ijk, off_ground, shape, 0, 0, 2, 4, 2)
    _, _, first = thin_sources(ijk, off_ground, shape, 0, 0, 2, 4, 0)
    assert len(uniform) == len(first) == 40 * 40 * 8 // 8
    offset = ijk[uniform] - (ijk[uniform] // 2 * 2 + 0.5)  # -0.5 or +0.5 voxel on each axis
    assert np.all(np.abs(offset.mean(axis=0)) < 0.05)
    assert np.allclose((ijk[first] - (ijk[first] // 2 * 2 + 0.5)).mean(axis=0), -0.5)
    order = np.random.default_rng(0).permutation(len(ijk))
    _, _, shuffled = thin_sources(ijk[order], off_ground, shape, 0, 0, 2, 4, 2)
    assert sorted(map(tuple, ijk[order][shuffled])) == sorted(map(tuple, ijk[uniform]))


def test_the_gicp_step_rotation_is_scipys_bit_for_bit():
    """se3_exp_left's rotation is scipy's Rotation.from_rotvec(...).as_matrix() to the last bit, on both sides of
    its small-angle series: poses and maps stay bit for bit what they were with scipy."""
    from scipy.spatial.transform import Rotation

    from occvo_core.registration.kernels.se3 import rotvec_matrix

    rng = np.random.default_rng(11)
    for n in range(20000):
        v = rng.normal(size=3)
        v *= 10 ** rng.uniform(-12, 0.5) / np.linalg.norm(v)
        if n % 5 == 0:
            v[n % 3] = 0.0
        assert np.array_equal(rotvec_matrix(v).view(np.uint64), Rotation.from_rotvec(v).as_matrix().view(np.uint64))
    assert np.array_equal(rotvec_matrix(np.zeros(3)), np.eye(3))


def test_an_ego_map_on_reused_buffers_equals_one_on_new_arrays():
    """EgoBuffers empties only the cells the last EgoMap wrote: a second, smaller build on them equals a fresh one."""
    from occvo_core.registration.ego_buffers import EgoBuffers
    from occvo_core.registration.local_map import EgoMap, window_margin
    from occvo_core.registration.voxel_map import VoxelPFilterMap

    rng = np.random.default_rng(5)
    voxel_map = VoxelPFilterMap(0.4)
    points = rng.uniform([-45, -45, -4], [45, 45, 4], (6000, 3))
    voxel_map.merge(points, rng.integers(0, 17, len(points)).astype(np.uint8), np.tile(np.eye(3), (6000, 1, 1)), 0)
    local = voxel_map.window(np.array([-130, -130, -15]), np.array([130, 130, 15]))
    margin, buffers = window_margin(4.0), EgoBuffers()
    for yaw, keep in ((0.3, 1.0), (-1.1, 0.5)):
        pose = np.eye(4)
        pose[:2, :2] = [[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]]
        pose[:3, 3] = [1.3, -2.1, 0.2]
        subset = rng.random(len(local)) < keep
        reused = EgoMap.around(local, pose, margin, subset=subset, buffers=buffers)
        fresh = EgoMap.around(local, pose, margin, subset=subset)
        for field in ("pos", "cov", "grid", "source"):
            assert np.array_equal(getattr(reused, field), getattr(fresh, field)), field
        assert (reused.grid >= 0).sum() > 100
