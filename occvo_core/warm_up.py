"""Every registration kernel compiled before the first real frame.

numba compiles a kernel at its first call, or loads it from its cache, which a fresh install or an upgrade lacks.
A worker meets some kernels only minutes into a drive: the first loop search, the first loop closure's map
correction, the first restore of an evicted tile; compiling one then holds a stream's next frames for seconds.
warm_up() calls them all on a made-up street, so a service pays once at start, before it takes frames.
"""

from __future__ import annotations

import time
from importlib import import_module

import numpy as np
from scipy.spatial.transform import Rotation

from occvo_core.config import OccVOConfig
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID
from occvo_core.odometry import OccVO
from occvo_core.registration import kernels, semantic_label_filter, voxel_pfilter
from occvo_core.registration.voxel_map import copied
from occvo_core.registration.voxel_rows import stored_rows
from occvo_core.state import stored

_FRAMES = 4
_STEP_M = 1.0  # the made-up ego drives this far per frame


def _street() -> tuple[np.ndarray, np.ndarray]:
    """World voxels (centres, labels) of a 100 m street: road, sidewalks, house fronts with doors every 6 m, trees,
    two parked cars."""
    v = OCC3D_GRID.voxel_size
    x = np.arange(-50.0, 50.0, v) + v / 2
    y = np.arange(-12.0, 12.0, v) + v / 2
    gx, gy = np.meshgrid(x, y, indexing="ij")
    ground = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, -0.8)])
    ground_labels = np.where(np.abs(gy.ravel()) < 5.0, 11, 13).astype(np.uint8)  # driveable surface, sidewalk
    pts, labels = [ground], [ground_labels]
    z = np.arange(-0.6, 5.0, v) + v / 2
    for side in (-10.2, 10.2):
        fx = x[(x % 6.0) > 1.2]  # doors: breaks that pin the street's length
        hx, hz = np.meshgrid(fx, z, indexing="ij")
        pts.append(np.column_stack([hx.ravel(), np.full(hx.size, side), hz.ravel()]))
        labels.append(np.full(hx.size, 15, np.uint8))  # manmade
    for tx in np.arange(-46.0, 50.0, 9.0):
        ty, tz = np.meshgrid([-6.2, -5.8], np.arange(-0.6, 4.0, v) + v / 2, indexing="ij")
        pts.append(np.column_stack([np.full(ty.size, tx), ty.ravel(), tz.ravel()]))
        labels.append(np.full(ty.size, 16, np.uint8))  # vegetation
    for cx, cy in ((4.0, 3.2), (-14.0, -3.2)):
        bx, by, bz = np.meshgrid(
            np.arange(cx - 2.0, cx + 2.0, v), np.arange(cy - 0.8, cy + 0.8, v), np.arange(-0.6, 0.8, v), indexing="ij"
        )
        pts.append(np.column_stack([bx.ravel(), by.ravel(), bz.ravel()]) + v / 2)
        labels.append(np.full(bx.size, 4, np.uint8))  # car
    return np.concatenate(pts), np.concatenate(labels)


def _frame(world: np.ndarray, labels: np.ndarray, i: int) -> OccupancyFrame:
    """The street seen from x = i * _STEP_M, as occupancy: voxel centres of the ego grid, one per voxel."""
    ijk = OCC3D_GRID.indices_of(world - [i * _STEP_M, 0.0, 0.0])
    inside = OCC3D_GRID.inside(ijk)
    ijk, lab = ijk[inside], labels[inside]
    ijk, first = np.unique(ijk, axis=0, return_index=True)
    return OccupancyFrame(OCC3D_GRID.centres_of(ijk), lab[first], index=i, stamp=0.5 * i)


def warm_up(config: OccVOConfig | None = None, threads: int = 1) -> dict[str, float | int]:
    """Call every registration kernel once (compiling it, or loading it from numba's cache). Returns the seconds
    taken and how many kernels were compiled or loaded. The odometry used here is thrown away."""
    t0 = time.perf_counter()
    before = kernels_ready()
    config = config or OccVOConfig()
    # loop closure from the second frame on, searching at every frame, so a few frames reach its search
    lc = config.loop_closure.model_copy(
        update={"enabled": True, "min_gap_frames": 1, "min_old_voxels": 1, "lock_share": 1.0, "search_every_frames": 1}
    )
    vo = OccVO(config.model_copy(update={"loop_closure": lc}), threads=threads)
    world, labels = _street()
    for i in range(_FRAMES):
        vo.step(_frame(world, labels, i))
    # bounded memory: the street behind goes to the caller's store, then a closed loop's map correction (a real
    # closure needs a drive that drifted), the merge after it, and the street back as the correction moved it
    blocks = {k: stored_rows(b) for k, b in vo.evict_tiles([vo.poses[-1][0, 3] + 80.0, 0.0], 60.0, 20.0).items()}
    correction = np.eye(4)
    correction[:3, :3] = Rotation.from_euler("z", 0.01).as_matrix()
    correction[:3, 3] = [1.5, 0.2, 0.0]
    vo.loop_closure.correct_map(list(vo.poses), correction @ vo.poses[-1], correction, len(vo.poses))
    vo.step(_frame(world, labels, _FRAMES))
    vo.restore_tiles(blocks)
    # the served map, whole and by tiles; a snapshot's copy and its restore
    vo.map_points()
    vo.map_points((np.array([-1, -1]), np.array([0, 0]), 20.0))
    state = {k: copied(v) for k, v in vo.state_dict(copy=False).items()}  # as the worker's snapshot copy
    OccVO(vo.config, threads=threads).load_state_dict(stored(state))  # in the form a store keeps
    after = kernels_ready()
    return {"seconds": round(time.perf_counter() - t0, 2), "kernels": len(after), "new": len(after - before)}


def kernels_ready() -> set[tuple[str, str]]:
    """(kernel, argument types) of every compiled kernel of occvo_core.registration. One that only other kernels
    call lists its types when compiled in this process, not when its callers came from the cache."""
    modules = [import_module(f"{kernels.__name__}.{m}") for m in kernels.MODULES] + [
        semantic_label_filter,
        voxel_pfilter,
    ]
    return {
        (f.py_func.__name__, str(sig))
        for m in modules
        for f in vars(m).values()
        if hasattr(f, "signatures")
        for sig in f.signatures
    }
