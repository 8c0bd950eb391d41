"""Occ3D's two visibility masks by ray casting on the 0.4 m grid. mask_lidar: the voxels a LiDAR ray crossed on its
way from the sensor to its point, and the point's own voxel. mask_camera: the voxels a camera ray crosses up to and
including the first occupied one (the renderer's DDA, occvo_core/cameras.py)."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.cameras import CameraRig, _cast_rays
from occvo_core.grid import OCC3D_GRID, GridSpec


@njit(cache=True)
def _trace_segments(starts, ends, lower, voxel, observed):
    """3D DDA (Amanatides-Woo) from each start to its end, clipped to the grid; every voxel crossed and the end's
    voxel marked. A NaN start marks the end's voxel only."""
    nx, ny, nz = observed.shape
    dims = np.array([nx, ny, nz])
    upper = lower + dims * voxel
    idx = np.empty(3, np.int64)
    step = np.empty(3, np.int64)
    tmax = np.empty(3)
    tdelta = np.empty(3)
    for n in range(starts.shape[0]):
        o, e = starts[n], ends[n]
        inside = True
        for a in range(3):
            idx[a] = int(np.floor((e[a] - lower[a]) / voxel))
            inside = inside and 0 <= idx[a] < dims[a]
        if inside:
            observed[idx[0], idx[1], idx[2]] = True
        if np.isnan(o[0]):
            continue
        d = e - o  # t in [0, 1] from start to end
        t0, t1 = 0.0, 1.0
        for a in range(3):  # slab test: the part of the segment inside the grid
            if abs(d[a]) < 1e-12:
                if o[a] < lower[a] or o[a] >= upper[a]:
                    t1 = -1.0
                continue
            ta, tb = (lower[a] - o[a]) / d[a], (upper[a] - o[a]) / d[a]
            if ta > tb:
                ta, tb = tb, ta
            t0, t1 = max(t0, ta), min(t1, tb)
        if t1 <= t0:
            continue
        for a in range(3):
            p = o[a] + d[a] * t0
            idx[a] = min(max(int(np.floor((p - lower[a]) / voxel)), 0), dims[a] - 1)
            if d[a] > 0:
                step[a], tmax[a], tdelta[a] = 1, (lower[a] + (idx[a] + 1) * voxel - o[a]) / d[a], voxel / d[a]
            elif d[a] < 0:
                step[a], tmax[a], tdelta[a] = -1, (lower[a] + idx[a] * voxel - o[a]) / d[a], -voxel / d[a]
            else:
                step[a], tmax[a], tdelta[a] = 0, np.inf, np.inf
        while True:
            observed[idx[0], idx[1], idx[2]] = True
            a = 0
            if tmax[1] < tmax[a]:
                a = 1
            if tmax[2] < tmax[a]:
                a = 2
            if tmax[a] >= t1:
                break
            idx[a] += step[a]
            if idx[a] < 0 or idx[a] >= dims[a]:
                break
            tmax[a] += tdelta[a]


def lidar_mask(points: np.ndarray, origins: np.ndarray, grid: GridSpec = OCC3D_GRID) -> np.ndarray:
    """(200,200,16) bool: voxels a ray from origins[n] to points[n] crossed or ended in (ego frame)."""
    observed = np.zeros(grid.shape, np.bool_)
    _trace_segments(
        np.ascontiguousarray(origins, np.float64),
        np.ascontiguousarray(points, np.float64),
        np.asarray(grid.lower, np.float64),
        float(grid.voxel_size),
        observed,
    )
    return observed


def camera_mask(semantics: np.ndarray, rig: CameraRig, stride: int = 8, grid: GridSpec = OCC3D_GRID) -> np.ndarray:
    """(200,200,16) bool: voxels a ray through every `stride`-th pixel of some camera crosses, up to and including
    the first occupied one (semantics != free)."""
    rays = rig.scaled(rig.width // stride, rig.height // stride)
    dirs = np.ascontiguousarray(rays.ray_directions())
    n, h, w = dirs.shape[:3]
    visible = np.zeros(grid.shape, np.bool_)
    _cast_rays(
        np.ascontiguousarray(rig.cam_to_ego[:, :3, 3]),
        dirs,
        np.ascontiguousarray(semantics, np.uint8),
        np.asarray(grid.lower, np.float64),
        float(grid.voxel_size),
        np.empty((n, h, w), np.uint8),
        np.empty((n, h, w), np.float64),
        np.zeros((n, h, w), np.int8),
        np.zeros((n, h, w, 3), np.int64),
        visible,
    )
    return visible
