"""Semantic Label Filter (the paper's Fig. 2): a GICP pair whose frame point and map voxel carry different labels
does not constrain the pose. Called where kernels.gicp pairs each source with its nearest map voxel."""

from __future__ import annotations

from numba import njit

from occvo_core.registration.kernels import CACHE


@njit(cache=CACHE, nogil=True, inline="always")
def semantic_label_filter(enabled, source_label, map_label):
    """Whether the pair (source, nearest map voxel) is kept."""
    return not enabled or source_label == map_label
