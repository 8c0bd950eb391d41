"""Voxel PFilter (the paper's Fig. 2): per map voxel, t0 (the frame it was first seen) and f (frames it was seen
in); its p-index is f over the frames it could have been seen in, and only voxels with p-index above a threshold
constrain registration. The map that keeps these counts is voxel_map.VoxelPFilterMap; its compiled merge is
kernels.voxel_pfilter."""

from __future__ import annotations

import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE


@njit(cache=CACHE, nogil=True)
def p_index(seen, frames):
    """p-index of voxels seen in `seen` of `frames` frames (at least one): at frame t, frames = t - t0; over the
    time a voxel was in view, frames = last - t0 + 1 (less the frames between visits). Scalars or arrays."""
    return seen / np.maximum(frames, 1)
