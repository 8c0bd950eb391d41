"""The ground of a sweep by height: per 2 m column, the lowest point's height, unless it lies well below the columns
around it (a stray return under the road: multipath, a drain), smoothed over the neighbours; a point within
`thickness` of it is ground. Geometry cannot tell the ground's kinds apart here (road, sidewalk, terrain, other
flat): every ground point is driveable surface (docs/datasets.md)."""

from __future__ import annotations

import warnings

import numpy as np
from scipy.ndimage import minimum_filter

CELL_M = 2.0
STRAY_M = 0.5  # a column's floor this far below its neighbourhood's median floor is a stray return


def ground_mask(points: np.ndarray, thickness: float = 0.3, reach_m: float = 60.0) -> np.ndarray:
    """(N,) True where a point (ego frame, z up from the ground under the car) lies on the ground."""
    n = int(np.ceil(2 * reach_m / CELL_M))
    ij = np.floor((points[:, :2] + reach_m) / CELL_M).astype(np.int64)
    inside = np.all((ij >= 0) & (ij < n), axis=1)
    floor = np.full((n, n), np.inf)
    np.minimum.at(floor, (ij[inside, 0], ij[inside, 1]), points[inside, 2])
    floor = _without_strays(floor)
    # a column with only a wall's or a car's points has no ground of its own: take its neighbours' lowest
    floor = np.minimum(floor, minimum_filter(floor, size=3, mode="nearest") + 0.3)
    height = np.full(len(points), np.inf)
    height[inside] = points[inside, 2] - floor[ij[inside, 0], ij[inside, 1]]
    return (height <= thickness) & (points[:, 2] < 1.0)


def _without_strays(floor: np.ndarray) -> np.ndarray:
    """Columns whose floor lies more than STRAY_M under the median floor of the 5x5 columns around them take that
    median instead: one stray return would otherwise sink the floor of nine columns (6 x 6 m of road not ground)."""
    seen = np.pad(np.where(np.isfinite(floor), floor, np.nan), 2, constant_values=np.nan)
    with warnings.catch_warnings():  # a column with no neighbour seen has no median: it stays as it is
        warnings.simplefilter("ignore", RuntimeWarning)
        median = np.nanmedian(np.lib.stride_tricks.sliding_window_view(seen, (5, 5)), axis=(2, 3))
    stray = np.isfinite(floor) & (floor < median - STRAY_M)
    return np.where(stray, median, floor)
