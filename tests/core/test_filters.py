"""The three filters of the paper on hand-built cases whose answers are known."""

import numpy as np
from scenes import box, car, frame, shell, town

from occvo_core import OccVO, OccVOConfig
from occvo_core.grid import OCC3D_GRID
from occvo_core.registration.dynamic_object_filter import cluster_objects, dynamic_object_filter
from occvo_core.registration.kernels.gicp_loop import gicp_linearise
from occvo_core.registration.kernels.grid import dense_index, surface_mask
from occvo_core.registration.voxel_map import VoxelPFilterMap


# -- semantic label filter --------------------------------------------------------------------------------------
def test_semantic_label_filter_drops_exactly_the_pairs_whose_labels_differ():
    points, labels = town()
    m = VoxelPFilterMap()
    map_labels = labels.copy()
    relabelled = np.flatnonzero(labels == 15)[::2]  # every other manmade voxel now says vegetation
    map_labels[relabelled] = 16
    m.merge(points, map_labels, np.tile(np.eye(3) * 0.1, (len(points), 1, 1)), 0)
    local = m.window(np.array([-110, -110, -10]), np.array([110, 110, 20]))
    covs = np.tile(np.eye(3) * 0.1, (len(points), 1, 1))
    args = (
        points,
        covs,
        labels.astype(np.int64),
        np.eye(3),
        np.zeros(3),
        local.pos,
        m.cov[local.rows],
        local.labels.astype(np.int64),
        local.usable,
        local.grid,
        local.origin,
        local.dims,
        0.4,
        1,
        0.3,
    )
    _, _, _, found_on, kept_on = gicp_linearise(*args, True, 0.0, np.empty(len(points), np.int64))
    _, _, _, found_off, kept_off = gicp_linearise(*args, False, 0.0, np.empty(len(points), np.int64))
    assert found_on == found_off == len(points)
    assert kept_off == len(points)
    assert kept_on == len(points) - len(relabelled)


def test_semantic_label_filter_removes_the_pull_of_the_wrong_class():
    """The map holds a pole row (manmade, y = 4.1 m). The car moves 0.3 m toward +y and now also sees a hedge
    (vegetation) 0.4 m behind the poles, new to the map: geometry alone pairs the hedge with the poles and is pulled
    short; with the filter those pairs are dropped and the poles alone give the true motion."""
    ground = box((-39, -39, -0.9), (39, 39, -0.9), 11)
    cross = box((3.0, -39, -0.5), (3.0, 39, 3.0), 15)  # pins x, no ends to pin y
    poles = box((-30, 4.1, -0.5), (30, 4.1, 3.0), 15)
    hedge = box((-30, 4.5, -0.5), (30, 4.5, 3.0), 16)
    join = lambda parts: (np.concatenate([p for p, _ in parts]), np.concatenate([l for _, l in parts]))  # noqa: E731
    pts0, lab0 = join((ground, cross, poles))
    pts1, lab1 = join((ground, cross, poles, hedge))
    pts1 = pts1 - np.array([0.0, 0.3, 0.0])  # voxel centres of a moved frame need not align with the old ones
    results = {}
    for semantic in (True, False):
        vo = OccVO(OccVOConfig().with_filters(semantic=semantic, dynamic=False, pfilter=False))
        vo.step(frame(pts0, lab0, 0))
        vo.step(frame(pts0, lab0, 1))  # standing still: the motion guess for the next frame is "no motion"
        results[semantic] = vo.step(frame(pts1, lab1, 2)).pose[1, 3]
    assert abs(results[True] - 0.3) < 0.02
    assert abs(results[False] - 0.3) > 0.05


# -- dynamic object filter --------------------------------------------------------------------------------------
def test_dynamic_object_filter_removes_moved_objects_and_keeps_parked_ones():
    parked_then, _ = car(10, -5)
    moving_then, _ = car(-10, 3)
    nudged_then, _ = car(20, 3)
    parked_now = parked_then + np.array([0.0, 0.0, 0.0])
    moving_now = moving_then + np.array([3.5, 0.0, 0.0])  # 3.5 m along its axis: moved
    nudged_now = nudged_then + np.array([0.4, 0.0, 0.0])  # 0.4 m: below the 2 m threshold, kept
    frame_pts = np.concatenate([parked_now, moving_now, nudged_now])
    map_pts = np.concatenate([parked_then, moving_then, nudged_then])
    found = dynamic_object_filter(
        frame_pts, map_pts, threshold_m=2.0, cluster_eps_m=1.0, min_cluster_points=5, quantile=0.8
    )
    n1, n2 = len(parked_now), len(moving_now)
    assert found.frame_objects == 3 and found.map_objects == 3
    assert (
        not found.frame_moved[:n1].any()
        and found.frame_moved[n1 : n1 + n2].all()
        and not found.frame_moved[n1 + n2 :].any()
    )
    assert (
        not found.map_moved[:n1].any() and found.map_moved[n1 : n1 + n2].all() and not found.map_moved[n1 + n2 :].any()
    )


def test_cluster_objects_separates_cars_and_ignores_specks():
    a, _ = car(0, 0)
    b, _ = car(0, 4)  # 2.2 m gap
    speck = np.array([[20.0, 20.0, 0.0], [20.2, 20.0, 0.0]])
    ids = cluster_objects(np.concatenate([a, b, speck]), eps=1.0, min_points=5)
    assert len(np.unique(ids[: len(a)])) == 1 and len(np.unique(ids[len(a) : len(a) + len(b)])) == 1
    assert ids[0] != ids[len(a)]
    assert (ids[-2:] == -1).all()


def test_odometry_drops_a_moving_car_from_the_map_and_keeps_the_parked_one():
    scene, scene_labels = town()
    parked, parked_l = car(12, -5.5)
    mover, mover_l = car(-14, 2.5)
    vo = OccVO()
    pts0 = np.concatenate([scene, parked, mover])
    lab0 = np.concatenate([scene_labels, parked_l, mover_l])
    vo.step(frame(pts0, lab0, 0))
    pts1 = np.concatenate([scene, parked, mover + np.array([4.0, 0, 0])])
    r = vo.step(frame(pts1, lab0, 1))
    assert np.allclose(r.pose, np.eye(4), atol=1e-3)
    assert r.pairs["dynamic_points"] > 0 and r.pairs["dynamic_map_voxels_removed"] > 0
    map_pts, map_lab = vo.map_points()
    cars = map_pts[map_lab == 4]
    old_mover = cars[:, 0] < -10.3  # the mover was at x -14..-9.8 and is now at -10..-5.8
    assert not old_mover.any()
    in_parked_box = lambda p: np.all(np.abs(p - np.array([14.1, -4.6, 0.25])) < np.array([2.5, 1.5, 1.0]), axis=1)  # noqa: E731
    parked_surface = in_parked_box(shell(pts0)).sum()  # the odometry keeps the surface voxels of a frame
    assert in_parked_box(cars).sum() >= 0.9 * parked_surface > 0


# -- voxel pfilter ----------------------------------------------------------------------------------------------
def _merge(m, pts, t, label=15):
    m.merge(np.asarray(pts, float), np.full(len(pts), label, np.uint8), np.tile(np.eye(3), (len(pts), 1, 1)), t)


def test_p_index_is_times_seen_over_frames_since_first_seen():
    m = VoxelPFilterMap()
    steady, blinking, once = [1.0, 1.0, 1.0], [5.0, 5.0, 1.0], [9.0, 9.0, 1.0]
    _merge(m, [steady, blinking, once], 0)
    _merge(m, [steady, blinking], 1)
    _merge(m, [steady], 2)
    _merge(m, [steady], 3)
    p = dict(zip(map(tuple, m.pos[: m._n].round(3)), m.p_index(4)))
    assert p[tuple(steady)] == 1.0  # 4 of 4
    assert p[tuple(blinking)] == 0.5  # 2 of 4
    assert p[tuple(once)] == 0.25  # 1 of 4
    local = m.window(np.array([-10, -10, -10]), np.array([40, 40, 10]), t=4)
    assert len(local) == 3
    assert local.usable.sum() == 1 and np.allclose(local.pos[local.usable][0], steady)  # only p-index > 0.5
    assert local.nearest(np.array([[5.1, 5.0, 1.0]]), 3)[1][0] == -1  # the blinking voxel is not paired with


def test_merge_is_a_p_index_weighted_average_per_voxel():
    m = VoxelPFilterMap(merge_radius_m=0.0)
    _merge(m, [[0.1, 0.1, 0.1]], 0)
    _merge(m, [[0.1, 0.1, 0.1]], 1)  # f = 2, t0 = 0
    # at t = 4 the voxel's p-index is 2/4: old weight f * p = 1; the new point has weight 1
    _merge(m, [[0.3, 0.1, 0.1]], 4)
    assert m._n == 1
    assert np.allclose(m.pos[0], [0.2, 0.1, 0.1])
    off = VoxelPFilterMap(merge_radius_m=0.0, pfilter=False)  # without the filter: a plain running mean
    for t, x in enumerate([0.1, 0.1, 0.3]):
        _merge(off, [[x, 0.1, 0.1]], t)
    assert np.allclose(off.pos[0], [(0.1 + 0.1 + 0.3) / 3, 0.1, 0.1])


def test_pfilter_off_lets_every_voxel_constrain_registration():
    m = VoxelPFilterMap(pfilter=False)
    _merge(m, [[1.0, 1, 1], [5.0, 5, 1]], 0)
    _merge(m, [[1.0, 1, 1]], 1)
    _merge(m, [[1.0, 1, 1]], 2)
    assert m.window(np.array([-10, -10, -10]), np.array([40, 40, 10]), t=3).usable.sum() == 2


def test_surface_mask_keeps_the_shell_of_a_solid_block():
    pts, _ = box((0, 0, 0), (2.0, 2.0, 2.0), 15)
    ijk = OCC3D_GRID.indices_of(pts)
    sides = ijk.max(axis=0) - ijk.min(axis=0) + 1
    shape = np.array(OCC3D_GRID.shape)
    keep = surface_mask(ijk, dense_index(ijk, shape), shape)
    assert keep.sum() == np.prod(sides) - np.prod(sides - 2)


def test_finished_map_keeps_voxels_seen_in_most_frames_while_in_view():
    m = VoxelPFilterMap()
    steady, blinking, passed = [1.0, 1.0, 1.0], [5.0, 5.0, 1.0], [9.0, 9.0, 1.0]
    _merge(m, [steady, blinking, passed], 0)
    _merge(m, [steady, passed], 1)
    _merge(m, [steady], 2)  # `passed` is behind the car from here on: its plain p-index decays, it stays in the map
    _merge(m, [steady, blinking], 3)
    pts, _ = m.points()
    kept = {tuple(p) for p in pts.round(3)}
    assert kept == {tuple(steady), tuple(passed)}  # blinking: 2 of the 4 frames from first to last sighting
    assert np.allclose(m.p_index(4)[m.pos[: m._n, 0].round(3) == 9.0], 0.5)
    every = VoxelPFilterMap(pfilter=False)
    for t in range(4):
        _merge(every, [steady, blinking] if t in (0, 3) else [steady], t)
    assert len(every.points()[0]) == 2


def test_near_any_agrees_with_a_kd_tree():
    from scipy.spatial import cKDTree

    from occvo_core.registration.kernels.nearest import near_any

    rng = np.random.default_rng(7)
    for n_points, spread in ((0, 10.0), (1, 10.0), (300, 10.0), (2000, 40.0)):
        points = rng.uniform(-spread, spread, (n_points, 3))
        queries = np.concatenate(
            [rng.uniform(-spread - 5, spread + 5, (500, 3)), points[:50] + rng.normal(0, 1.2, (min(50, n_points), 3))]
        )
        want = (cKDTree(points).query(queries)[0] <= 2.0) if n_points else np.zeros(len(queries), bool)
        assert np.array_equal(near_any(queries, points, 2.0), want)


def test_moving_map_voxels_drops_ghosts_of_older_voxels_and_cell_clashes():
    """A loop closure moves the recent map; a moved voxel that lands on an older voxel of its label (within the
    ghost radius) or in an occupied cell is that voxel seen through drift, and goes."""
    m = VoxelPFilterMap(merge_radius_m=0.0)
    old = [[10.1, 10.1, 1.1], [20.1, 20.1, 1.1]]
    for t in range(3):
        _merge(m, old, t)
    _merge(m, [[15.1, 10.1, 1.1], [25.1, 20.1, 1.1], [40.1, 40.1, 1.1]], 10, label=15)
    _merge(m, [[35.1, 40.1, 1.1]], 10, label=16)
    recent = np.flatnonzero(m.born[: m._n] >= 10)
    shift = np.array([-5.0, 0.0, 0.0])
    # 15.1 -> 10.1: old voxel's cell; 25.1 -> 20.1 likewise; 40.1 -> 35.1: free; 35.1 (other label) -> 30.1: free
    m.move(
        recent,
        np.tile(np.eye(3), (len(recent), 1, 1)),
        np.tile(shift, (len(recent), 1)),
        ghost_radius_m=1.0,
        born_before=5,
    )
    kept = {tuple(p) for p in m.pos[: m._n][m.alive[: m._n]].round(2)}
    assert kept == {(10.1, 10.1, 1.1), (20.1, 20.1, 1.1), (35.1, 40.1, 1.1), (30.1, 40.1, 1.1)}
    assert m.pop_changed_region() is None  # moved anywhere: the caller re-tiles everything
    # a ghost one cell off: dropped only when an old voxel of its label is within the radius
    for radius, expect in ((1.0, 1), (0.0, 0)):
        m2 = VoxelPFilterMap(merge_radius_m=0.0)
        for t in range(3):
            _merge(m2, [[10.1, 10.1, 1.1]], t)
        _merge(m2, [[15.1, 10.1, 1.1]], 10)  # -> (10.6, 10.4): 0.58 m from the old voxel, in the next cell
        _merge(m2, [[15.1, 10.5, 1.1]], 10, label=16)  # -> (10.6, 10.8): as near, another class
        recent = np.flatnonzero(m2.born[: m2._n] >= 10)
        assert (
            m2.move(
                recent,
                np.tile(np.eye(3), (2, 1, 1)),
                np.tile([-4.5, 0.3, 0.0], (2, 1)),
                ghost_radius_m=radius,
                born_before=5,
            )
            == expect
        )
        assert m2.alive[recent[1]]


def test_moving_map_voxels_in_place_matches_the_rule_written_out():
    """VoxelPFilterMap.move (kernels.move_rows, claim_cells, a ghost search only near the old map) against its rule
    in plain numpy, on random maps and random per-group motions: R p + t and R C R^T; a moved voxel whose cell holds
    a voxel that did not move, or a moved one before it in turn_before's order, goes; one moved farther than a voxel
    whose nearest reliable old voxel (born before born_before) lies within the ghost radius with its label goes."""
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(3)
    for trial in range(6):
        m = VoxelPFilterMap(merge_radius_m=0.0)
        for t in range(12):
            pts = rng.uniform([-12, -12, 0], [12, 12, 3], (150, 3))
            m.merge(
                pts, rng.integers(13, 16, len(pts)).astype(np.uint8), np.tile(np.eye(3) * 0.01, (len(pts), 1, 1)), t
            )
        n = m._n
        rows = np.flatnonzero(m.alive[:n] & (m.born[:n] >= 6))
        groups = rng.integers(0, 4, len(rows))
        rot = Rotation.from_rotvec(rng.normal(0, 0.05, (4, 3))).as_matrix()
        trans = rng.normal(0, 1.0, (4, 3))
        before = {k: v.copy() for k, v in m.state().items()}
        dropped = m.move(rows, rot, trans, ghost_radius_m=1.0, born_before=6, group=groups)

        pos = np.einsum("nij,nj->ni", rot[groups], before["pos"][rows]) + trans[groups]
        cov = rot[groups] @ before["cov"][rows] @ rot[groups].transpose(0, 2, 1)
        assert np.allclose(m.pos[rows], pos, atol=1e-12) and np.allclose(m.cov[rows], cov, atol=1e-12)
        keys = np.floor(m.pos[rows] / m.voxel).astype(np.int64)
        assert np.array_equal(m.keys[rows], keys)
        still = np.setdiff1d(np.flatnonzero(before["alive"]), rows)
        held = {tuple(k) for k in before["keys"][still]}

        def turn_order(p):  # kernels.turns.turn_before: the least of the point's four turns about z, then z
            x, y = p[0], p[1]
            return (*min([(x, y), (-y, x), (-x, -y), (y, -x)]), p[2])

        first = {}
        for a, k in enumerate(map(tuple, keys)):
            if k not in held and (k not in first or turn_order(m.pos[rows[a]]) < turn_order(m.pos[rows[first[k]]])):
                first[k] = a
        keep = np.zeros(len(rows), bool)
        keep[list(first.values())] = True
        f, last, t0 = before["f"][still], before["last"][still], before["t0"][still]
        old = still[(f / np.maximum(last - t0 + 1, 1) > m.p_index_threshold) & (before["born"][still] < 6)]
        far = np.linalg.norm(m.pos[rows] - before["pos"][rows], axis=1) > m.voxel
        for a in np.flatnonzero(keep & far):
            d = np.linalg.norm(before["pos"][old] - m.pos[rows[a]], axis=1)
            if len(d) and d.min() <= 1.0 and before["label"][old[d.argmin()]] == m.label[rows[a]]:
                keep[a] = False
        assert np.array_equal(m.alive[rows], keep), trial
        assert dropped == int((~keep).sum()) and 0 < dropped < len(rows)


def _window_of(m, t):
    return m.window(np.array([-100, -100, -10]), np.array([100, 100, 20]), t)


def test_a_voxel_back_in_the_registration_window_keeps_its_p_index():
    """The p-index counts the frames a voxel could be seen in: frames it spent outside every registration window
    (a place driven away from and come back to) do not wear it down, frames in the window without a sighting do."""
    m = VoxelPFilterMap()
    for t in range(4):  # seen in frames 0..3
        m.entered(*m.enter(_window_of(m, t), t), t)
        _merge(m, [[5.1, 5.1, 1.1]], t)
    far = np.array([1000, 1000, 0])
    for t in range(4, 10):  # the window is elsewhere
        m.entered(*m.enter(m.window(far, far + 10, t), t), t)
    local = _window_of(m, 10)
    rows, away = m.enter(local, 10)
    assert away.tolist() == [6] and local.p_index[0] == 1.0 and local.usable[0]  # 4 sightings in 4 frames in view
    assert m.p_index(10)[0] == 4 / 10  # the map itself is untouched until the frame is committed
    m.entered(rows, away, 10)
    assert m.p_index(10)[0] == 1.0 and m.persistent()[0]
    for t in range(10, 14):  # in the window, not seen: these frames count against it
        m.entered(*m.enter(_window_of(m, t), t), t)
    assert m.p_index(14)[0] == 4 / 8 and not _window_of(m, 14).usable[0]


def test_a_place_seen_in_glimpses_on_two_visits_stays_in_the_served_map():
    """The served map (persistent()) counts each visit from a voxel's first to its last sighting: the frames in view
    after its last sighting on one visit and before its first on the next lie between visits, as those before its
    first sighting do. Within a visit a voxel seen in few frames is still left out, and loop closure's old map
    (persistent_rows) still counts every frame in view: a voxel seen only in glimpses is no anchor."""
    m = VoxelPFilterMap()
    glimpsed, blinking, elsewhere = [5.1, 5.1, 1.1], [7.1, 7.1, 1.1], [1000.1, 1000.1, 1.1]
    far = np.array([990, 990, 0])
    for t in range(30):  # visit 1: frames 0..9, away 10..19, visit 2: 20..29
        window = m.window(far, far + 20, t) if 10 <= t < 20 else _window_of(m, t)
        m.entered(*m.enter(window, t), t)
        seen = ([glimpsed] if t in (0, 1, 25, 26) else []) + ([blinking] if t in (0, 8) else [])
        _merge(m, seen or [elsewhere], t)
    rows = {tuple(np.round(m.pos[r], 1)): r for r in range(m._n)}
    g, b = rows[tuple(glimpsed)], rows[tuple(blinking)]
    assert m.f[g] == 4 and m.between[g] == 13  # frames 2..9 and 20..24 were in view without a sighting
    assert m.persistent()[g] and not m.persistent_rows(np.array([g]))[0]  # 4 of 4 in view; 4 of 17 for the old map
    assert m.f[b] == 2 and not m.persistent()[b]  # 2 of 9 frames of one visit
    assert len(m.points()[0]) == int(m.persistent().sum())


def test_a_frame_off_the_old_map_leaves_it_alone_and_one_on_it_moves_none_of_it_and_adds_no_second_layer():
    """Loop closure's old map in the voxel pfilter merge: a drifted frame neither drags old voxels nor counts them
    seen; a frame following the old map counts its points in or near old voxels as sightings of them, neither
    moving them (each lap's registration error would creep into the map every later lap follows) nor adding a voxel
    beside them."""

    def old_map():
        m = VoxelPFilterMap(observe_radius_m=0.45)
        for t in range(3):
            _merge(m, [[5.1, 5.1, 1.1], [9.1, 9.1, 1.1]], t)
        return m

    points = [
        [5.15, 5.0, 1.1],  # in the first old voxel's cell
        [9.1, 9.45, 1.1],  # next cell, 0.35 m from the second old voxel
        [20.1, 20.1, 1.1],
    ]  # nowhere near
    off = old_map()
    rows = off.merge(
        np.array(points),
        np.full(3, 15, np.uint8),
        np.tile(np.eye(3), (3, 1, 1)),
        200,
        old_born_before=100,
        on_old=False,
    )
    assert rows[0] == -1 and rows[1] >= 2 and rows[2] >= 2  # no point lands in an old voxel
    assert off.f[:2].tolist() == [3, 3] and off.last[:2].tolist() == [2, 2]  # not seen, not moved
    assert np.allclose(off.pos[:2], [[5.1, 5.1, 1.1], [9.1, 9.1, 1.1]]) and len(off) == 4
    on = old_map()
    rows = on.merge(
        np.array(points), np.full(3, 15, np.uint8), np.tile(np.eye(3), (3, 1, 1)), 200, old_born_before=100, on_old=True
    )
    assert rows[0] == -1 and rows[1] == -1 and rows[2] == 2  # seen, seen, new
    assert on.f[:2].tolist() == [4, 4] and on.last[:2].tolist() == [200, 200]  # both seen once at frame 200
    assert np.allclose(on.pos[:2], [[5.1, 5.1, 1.1], [9.1, 9.1, 1.1]]) and len(on) == 3
    plain = old_map()  # without an old map both nearby points make voxels of their own
    plain.merge(np.array(points), np.full(3, 15, np.uint8), np.tile(np.eye(3), (3, 1, 1)), 200)
    assert len(plain) == 4


def test_map_array_copies_and_compaction_without_the_gil_equal_numpys():
    """copied() and the in-place row gather of compact() give numpy's bytes, for every dtype and shape the map holds."""
    from occvo_core.registration.kernels.map_rows import gather_row_bytes
    from occvo_core.registration.voxel_map import _row_bytes, copied

    rng = np.random.default_rng(7)
    n = 200_000  # over copied()'s 1 MB threshold, so the kernel runs
    for a in (
        rng.random((n, 3, 3)),
        rng.integers(-9, 9, (n, 18)).astype(np.int32),
        rng.random(n) > 0.5,
        rng.integers(0, 18, n).astype(np.uint8),
        rng.random(5),
        np.zeros((0, 3)),
    ):
        b = copied(a)
        assert b.dtype == a.dtype and b.shape == a.shape and np.array_equal(a, b) and not np.shares_memory(a, b)
        if len(a):
            keep = np.sort(rng.choice(len(a), len(a) // 3, replace=False))
            arr = a.copy()
            gather_row_bytes(_row_bytes(arr), keep)
            assert np.array_equal(arr[: len(keep)], a[keep]) and np.array_equal(arr[len(keep) :], a[len(keep) :])


def test_compaction_reclaims_dead_rows_before_the_map_would_have_to_grow():
    """Dead rows are reclaimed once they are a third of the rows, or once the rows near the capacity (the arrays
    would double otherwise); the live rows keep their order and content."""
    from occvo_core.registration.voxel_map import VoxelPFilterMap

    def filled(n, dead):
        m = VoxelPFilterMap()
        m._n = n
        m.alive[:n] = True
        m.keys[:n, 0] = np.arange(n)
        m.alive[dead] = False
        return m

    cap = len(VoxelPFilterMap().pos)
    rng = np.random.default_rng(3)
    few = rng.choice(cap // 2, cap // 20, replace=False)  # 10% of the rows dead
    m = filled(cap // 2, few)
    m.compact()
    assert m._n == cap // 2  # half full, few dead: left alone
    near = rng.choice(cap - cap // 16, cap // 20, replace=False)
    m = filled(cap - cap // 16, near)
    m.compact()
    live = np.setdiff1d(np.arange(cap - cap // 16), near)
    assert m._n == len(live) and np.array_equal(m.keys[: m._n, 0], live) and m.alive[: m._n].all()
    assert len(m.pos) == cap  # and it never grew
    m = filled(cap - cap // 16, near[:100])  # near the capacity, but too few dead rows to be worth a copy of it all
    m.compact()
    assert m._n == cap - cap // 16


def test_a_window_finds_every_row_a_scan_would_after_merges_moves_puts_and_compaction():
    """window() reads only the row blocks whose key box reaches it: after each way rows are made, moved, put back or
    renumbered, it returns exactly the live rows, in row order, that a scan of every row finds."""
    from occvo_core.registration.kernels.row_blocks import BLOCK_ROWS

    def scanned(m, lower, upper):
        keys, n = m.keys[: m._n], m._n
        return np.flatnonzero(m.alive[:n] & np.all((keys >= lower) & (keys <= upper), axis=1))

    def check(m):
        for lower, upper in (([-5, -5, -2], [40, 5, 3]), ([-5, 60, -2], [600, 90, 3]), ([-5, -5, -1], [4200, 300, 1])):
            lower, upper = np.array(lower), np.array(upper)
            assert np.array_equal(m.window(lower, upper).rows, scanned(m, lower, upper))

    m = VoxelPFilterMap(0.4, merge_radius_m=0.0)
    x = np.arange(4 * BLOCK_ROWS) * 0.4 + 0.2  # a line of voxels, made over four frames: several blocks
    for t, part in enumerate(np.array_split(x, 4)):
        pts = np.stack([part, np.full(len(part), 0.2), np.full(len(part), 0.2)], axis=1)
        m.merge(pts, np.zeros(len(pts), np.uint8), np.tile(np.eye(3), (len(pts), 1, 1)), t)
    check(m)
    rows = np.arange(10, 10 + BLOCK_ROWS // 2)  # moved 30 m aside, out of their blocks' boxes
    shift = np.tile([0.0, 30.0, 0.0], (len(rows), 1))
    assert m.move(rows, np.tile(np.eye(3), (len(rows), 1, 1)), shift) == 0
    check(m)
    block = m.take(np.arange(2 * BLOCK_ROWS, 2 * BLOCK_ROWS + 50), 4)
    block["keys"] = block["keys"] + [0, 200, 0]  # put back 80 m aside
    block["pos"] = block["pos"] + [0.0, 80.0, 0.0]
    assert m.put(block, 5) == 50
    check(m)
    m.remove(np.arange(0, m._n, 2))
    m.compact()
    check(m)


def test_grid_clusters_are_the_connected_components_of_pairs_within_eps():
    """Each pair tried once, cells a point cannot reach skipped: still every pair within eps joined (lattice points
    lie exactly eps apart), and each cluster named by its smallest index."""
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    from occvo_core.registration.kernels.clusters import grid_clusters

    rng = np.random.default_rng(3)
    for n_points, spread, eps, lattice in ((1, 5.0, 1.0, False), (400, 6.0, 1.0, False), (600, 8.0, 0.4, True)):
        points = rng.uniform(-spread, spread, (n_points, 3))
        if lattice:
            points = np.round(points / eps) * eps + 0.1
        pairs = cKDTree(points).query_pairs(eps * (1 + 1e-12), output_type="ndarray")
        d2 = ((points[pairs[:, 0]] - points[pairs[:, 1]]) ** 2).sum(axis=1)
        pairs = pairs[d2 <= eps * eps]  # the kernel's test, exactly
        adjacency = np.zeros((n_points, n_points), bool)
        adjacency[pairs[:, 0], pairs[:, 1]] = True
        _, component = connected_components(adjacency, directed=False)
        smallest = np.full(component.max() + 1, n_points)
        np.minimum.at(smallest, component, np.arange(n_points))
        assert np.array_equal(grid_clusters(points, eps), smallest[component])
