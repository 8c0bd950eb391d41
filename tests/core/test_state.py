"""Odometry state for durable storage and paging: state_dict round trip, tile eviction and restore."""

from __future__ import annotations

import dataclasses
import io

import numba
import numpy as np
import pytest

from occvo_core import OccVO, OccVOConfig
from occvo_core.errors import ConfigError
from occvo_core.sim import SyntheticScene
from occvo_core.state import stored


@pytest.fixture(scope="module")
def scene():
    return SyntheticScene(seed=5, frames=12)


def _through_bytes(state: dict) -> dict:
    buf = io.BytesIO()
    np.savez(buf, **state)
    return dict(np.load(io.BytesIO(buf.getvalue())))


@pytest.mark.parametrize("form", [dict, stored], ids=["arrays", "stored"])
def test_resume_from_state_dict_is_bit_identical(scene, form):
    """From the state's arrays, and from the form a store keeps (smaller): the same run on."""
    whole = OccVO()
    for i in range(len(scene)):
        whole.step(scene[i])
    first = OccVO()
    for i in range(6):
        first.step(scene[i])
    resumed = OccVO()
    resumed.load_state_dict(_through_bytes(form(first.state_dict())))
    for i in range(6, len(scene)):
        resumed.step(scene[i])
    assert np.array_equal(resumed.poses, whole.poses)
    assert resumed.frame_indices == whole.frame_indices
    for a, b in zip(resumed.map_points(), whole.map_points()):
        assert np.array_equal(a, b)


def test_the_stored_form_keeps_the_class_counts_nonzero_entries_and_int32_keys(scene):
    vo = OccVO()
    for i in range(3):
        vo.step(scene[i])
    state = vo.state_dict()
    kept = stored(state)
    assert "map.counts" not in kept and kept["map.keys"].dtype == np.int32
    assert len(kept["map.counts.at"]) == np.count_nonzero(state["map.counts"])
    assert sum(a.nbytes for a in kept.values()) < 0.8 * sum(a.nbytes for a in state.values())
    back = OccVO()
    back.load_state_dict(_through_bytes(kept))
    for name in ("counts", "keys"):
        assert np.array_equal(back.map.state(copy=False)[name], state[f"map.{name}"])


def test_state_of_another_config_is_refused(scene):
    vo = OccVO()
    vo.step(scene[0])
    other = OccVO(OccVOConfig().with_filters(pfilter=False))
    with pytest.raises(ConfigError, match="another OccVOConfig"):
        other.load_state_dict(vo.state_dict())


def _voxels(vo: OccVO) -> np.ndarray:
    """Every live voxel as rows of (key, position, label, f, frames from first to last sighting), sorted."""
    m, n = vo.map, vo.map._n
    live = m.alive[:n]
    table = np.column_stack(
        [m.keys[:n][live], m.pos[:n][live], m.label[:n][live], m.f[:n][live], m.last[:n][live] - m.t0[:n][live]]
    )
    return table[np.lexsort(table.T[::-1])]


def test_evicted_tiles_leave_the_working_map_and_come_back_whole(scene):
    vo = OccVO()
    for i in range(8):
        vo.step(scene[i])
    before = _voxels(vo)
    ego = vo.poses[-1][:2, 3]
    tiles_before = vo.resident_tiles(20.0)
    live = vo.map.alive[: vo.map._n]
    pos_before = vo.map.pos[: vo.map._n][live].copy()
    tile_of = np.floor(pos_before[:, :2] / 20.0).astype(np.int64)
    blocks = vo.evict_tiles(ego, 40.0, 20.0)
    assert blocks, "the first frames' map reaches beyond 40 m of the last pose"
    for (ix, iy), block in blocks.items():  # each block: every voxel of its tile, in map row order
        np.testing.assert_array_equal(block["pos"], pos_before[(tile_of[:, 0] == ix) & (tile_of[:, 1] == iy)])
    resident = vo.resident_tiles(20.0)
    assert resident.isdisjoint(blocks) and resident | set(blocks) == tiles_before
    for ix, iy in resident:  # every resident tile touches the disc
        dx = max(ix * 20.0 - ego[0], 0, ego[0] - (ix + 1) * 20.0)
        dy = max(iy * 20.0 - ego[1], 0, ego[1] - (iy + 1) * 20.0)
        assert np.hypot(dx, dy) <= 40.0
    evicted = sum(len(b["keys"]) for b in blocks.values())
    assert len(vo.map) == len(before) - evicted
    assert vo.restore_tiles(blocks) == evicted
    assert np.array_equal(_voxels(vo), before)  # same voxels, labels and sighting history


def test_a_restored_voxel_keeps_its_p_index_of_the_time_it_was_in_view(scene):
    vo = OccVO()
    for i in range(6):
        vo.step(scene[i])
    blocks = vo.evict_tiles(vo.poses[-1][:2, 3], 30.0, 20.0)
    taken = {name: np.concatenate([b[name] for b in blocks.values()]) for name in ("t0", "f", "last", "keys")}
    in_view = taken["f"] / (taken["last"] - taken["t0"] + 1)
    for i in range(6, 9):
        vo.step(scene[i])
    t_back = len(vo.poses)
    n_before = vo.map._n
    persistent_before = vo.map.persistent().sum()
    added = vo.restore_tiles(blocks)
    assert 0 < added <= len(in_view)
    rows = np.arange(n_before, n_before + added)
    # the restored voxels are those whose cells the map had not filled again meanwhile, in block order
    held = {tuple(k) for k in vo.map.keys[:n_before][vo.map.alive[:n_before]]}
    kept = np.array([tuple(k) not in held for k in taken["keys"]])
    assert kept.sum() == added
    assert np.allclose(vo.map.p_index(t_back)[rows], in_view[kept])  # as if last seen the frame before
    assert np.all(vo.map.last[rows] == t_back - 1)
    assert vo.map.persistent().sum() == persistent_before + np.count_nonzero(in_view[kept] > 0.5)


def test_retiling_the_changed_region_equals_tiling_the_whole_map():
    """The registration worker re-cuts only the tiles a frame changed; through steps with moving cars (the dynamic
    object filter removes map voxels), evictions and restores, that must equal cutting the whole map every frame."""
    from occvo_core.map_tiles import retile_region, tiles_from_map

    scene = SyntheticScene(seed=3, frames=24)
    vo, tiles, cold, redone_share = OccVO(), {}, {}, []
    for i in range(len(scene)):
        if i == 16:
            vo.restore_tiles(cold)  # back near the start: the evicted map returns
        vo.step(scene[i])
        points, labels = vo.map_points()
        tiles, redone = retile_region(tiles, vo.map_points, vo.pop_changed_region(), 20.0)
        whole = tiles_from_map(points, labels, 20.0)
        assert tiles.keys() == whole.keys(), f"frame {i}"
        for k in whole:
            assert np.array_equal(tiles[k][0], whole[k][0]) and np.array_equal(tiles[k][1], whole[k][1]), (
                f"frame {i} tile {k}"
            )
        redone_share.append(len(redone) / max(len(whole), 1))
        if i in (8, 12):
            blocks = vo.evict_tiles(vo.poses[-1][:2, 3], 40.0, 20.0)
            cold.update(blocks)
            tiles = {k: v for k, v in tiles.items() if k not in blocks}  # as the worker drops evicted tiles
    assert cold, "some tiles were evicted"
    assert min(redone_share[1:]) < 1.0, "a frame re-cut fewer tiles than the whole map"


def _run(scene, threads: int):
    vo, steps = OccVO(threads=threads), []
    for i in range(len(scene)):
        r = vo.step(scene[i])
        steps.append((r.pairs, vo.pop_changed_region()))
    return vo, steps


def _same_run(a, b) -> None:
    (vo_a, steps_a), (vo_b, steps_b) = a, b
    assert np.array_equal(vo_a.poses, vo_b.poses)
    for (pairs_a, box_a), (pairs_b, box_b) in zip(steps_a, steps_b):
        assert pairs_a == pairs_b
        assert (box_a is None and box_b is None) or np.array_equal(box_a, box_b)
    state_a, state_b = vo_a.state_dict(), vo_b.state_dict()
    assert state_a.keys() == state_b.keys()
    for k in state_a:
        assert np.array_equal(state_a[k], state_b[k]), k


needs_two_cores = pytest.mark.skipif(
    numba.config.NUMBA_NUM_THREADS < 2, reason="one core here: there is no second kernel thread to compare with"
)


def test_the_order_of_a_frames_points_changes_nothing():
    """A frame is a set of voxels: the same voxels in another order (a client, another reader) give the same poses
    and map, bit for bit. Before the odometry put them in grid order, thinning kept the first voxel of each block in
    the order given, and reversing scene-0101's points took its APE from 0.285 to 0.092 m (scene-0268: 0.103 to
    0.575)."""
    scene = SyntheticScene(seed=3, frames=10)
    rng = np.random.default_rng(0)
    given, shuffled = OccVO(), OccVO()
    for i in range(len(scene)):
        frame = scene[i]
        order = rng.permutation(len(frame.points))
        given.step(frame)
        shuffled.step(dataclasses.replace(frame, points=frame.points[order], labels=frame.labels[order]))
    assert np.array_equal(shuffled.poses, given.poses)
    for a, b in zip(shuffled.map_points(), given.map_points()):
        assert np.array_equal(a, b)


@needs_two_cores
def test_kernel_threads_do_not_change_a_bit():
    """The parallel kernels sum over fixed slices and number new voxels serially: one core or two, the same poses,
    filter counts, changed regions and map state (a scene with moving cars, so the dynamic object filter acts)."""
    scene = SyntheticScene(seed=3, frames=16)
    one, two = _run(scene, 1), _run(scene, 2)
    assert sum(pairs.get("dynamic_map_voxels_removed", 0) for pairs, _ in one[1]) > 0
    _same_run(one, two)


@needs_two_cores
def test_streams_in_threads_run_parallel_kernels_at_once():
    """The registration worker steps its streams in threads of one process: parallel kernels launched from two
    threads at once must neither abort nor mix their results."""
    from concurrent.futures import ThreadPoolExecutor

    scenes = [SyntheticScene(seed=s, frames=10) for s in (1, 2)]
    alone = [_run(s, 2) for s in scenes]
    with ThreadPoolExecutor(2) as pool:
        together = list(pool.map(lambda s: _run(s, 2), scenes))
    for a, b in zip(alone, together):
        _same_run(a, b)
    assert not np.array_equal(alone[0][0].poses, alone[1][0].poses)


def test_negative_kernel_threads_are_refused():
    with pytest.raises(ConfigError, match="threads"):
        OccVO(threads=-1)
