"""Stamp association as evo does it (evo.core.sync.associate_trajectories, nearest time): each pose of the trajectory
with fewer poses (the second one when they have as many) takes the other's pose nearest in time, within max_diff
seconds, or none."""

from __future__ import annotations

import numpy as np

MAX_DIFF_S = 0.01  # evo's --t_max_diff default


def matching_time_indices(stamps_1, stamps_2, max_diff: float = MAX_DIFF_S) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i1, i2) of the stamps_1 with a stamps_2 within max_diff, and of that nearest stamps_2 (ties: the
    earlier one), as evo's matching_time_indices gives them."""
    s1, s2 = np.asarray(stamps_1, float), np.asarray(stamps_2, float)
    if not np.all(np.diff(s2) >= 0):  # unsorted: evo's linear search
        diffs = np.abs(s2[None, :] - s1[:, None])
        best = diffs.argmin(axis=1)
        ok = diffs[np.arange(len(s1)), best] <= max_diff
        return np.flatnonzero(ok), best[ok]
    above = np.minimum(np.searchsorted(s2, s1, side="right"), len(s2) - 1)
    diff_ub = s2[above] - s1
    diff_lb = np.where(above > 0, s1 - s2[above - 1], np.inf)
    take_ub = (diff_ub <= max_diff) & (diff_ub < diff_lb)
    take_lb = ~take_ub & (diff_lb <= max_diff) & (diff_lb <= diff_ub)
    ok = (s1 >= s2[0] - max_diff) & (s1 <= s2[-1] + max_diff) & (take_ub | take_lb)
    best = np.where(take_ub, above, above - 1)
    return np.flatnonzero(ok), best[ok]


def associate(stamps_1, stamps_2, max_diff: float = MAX_DIFF_S) -> tuple[np.ndarray, np.ndarray]:
    """Indices into the first and the second trajectory of their associated poses, in the order of the shorter."""
    if len(stamps_2) > len(stamps_1):
        return matching_time_indices(stamps_1, stamps_2, max_diff)
    ids_2, ids_1 = matching_time_indices(stamps_2, stamps_1, max_diff)
    return ids_1, ids_2
