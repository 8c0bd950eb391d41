"""The map around the ego, for recordings that log the map as a run goes: a drive's whole map logged every few
frames makes a recording quadratic in the drive; the map within reach of the ego is bounded (the whole map is logged
once, at the end)."""

from __future__ import annotations

import numpy as np

# a frame's own reach (its grid is 80 m wide), in whole tiles: from the first frame on, about one frame's area
MAP_REACH_M, MAP_TILE_M = 40.0, 20.0


def map_near(odometry, pose: np.ndarray, reach_m: float = MAP_REACH_M, tile_m: float = MAP_TILE_M):
    """(points, labels) of the map's x-y tiles within reach_m of the pose."""
    xy = np.asarray(pose)[:2, 3]
    lo = np.floor((xy - reach_m) / tile_m).astype(np.int64)
    hi = np.floor((xy + reach_m) / tile_m).astype(np.int64)
    return odometry.map_points((lo, hi, tile_m))
