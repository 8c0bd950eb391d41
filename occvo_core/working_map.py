"""The bounded working map: on a long drive the odometry keeps only the map near the ego, as square x-y tiles
(ix, iy) = floor(xy / tile_m). The paging policy lives here, the store of paged-out tiles with the caller:

- after a frame, every tile wholly farther than the working radius from the ego leaves the map (evict_tiles);
- a cold tile comes back once the ego is within radius - tile_m of it (tiles_near: one tile of hysteresis, so no
  tile flaps in and out), or as soon as a frame's points reach into it (tiles_reached: the tile stays whole);
- a tile comes back moved by the loops closed while it was out (restore_tiles).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np

from occvo_core.map_tiles import pack_tiles, tile_distance

if TYPE_CHECKING:
    from occvo_core.odometry import OccVO

Tile = tuple[int, int]
REACH_MARGIN_M = 1.0  # a map voxel merged with a frame point moves at most this far


def changed_map(vo: OccVO, tile_m: float) -> tuple:
    """(region, points, labels): the x-y box of the map the last frame changed (None: anywhere) and the map's points
    in the tiles it overlaps, copied (what a caller cuts into tiles and publishes)."""
    region = vo.pop_changed_region()
    if region is None:
        return (None, *vo.map_points())
    if region[0] > region[2]:  # nothing changed
        return (region, np.zeros((0, 3)), np.zeros(0, np.uint8))
    lo = np.floor(np.asarray(region[:2]) / tile_m).astype(np.int64)
    hi = np.floor(np.asarray(region[2:]) / tile_m).astype(np.int64)
    return (region, *vo.map_points((lo, hi, tile_m)))


def evict_tiles(vo: OccVO, center_xy, radius_m: float, tile_m: float) -> dict[Tile, dict[str, np.ndarray]]:
    """Take every tile wholly farther than radius_m from center_xy out of the odometry's map; returns {tile: voxels}
    for the caller to keep (bounded memory on long drives)."""
    return vo.map.take_far_tiles(center_xy, radius_m, tile_m, len(vo.poses))


def has_far_tiles(vo: OccVO, center_xy, radius_m: float, tile_m: float) -> bool:
    """Whether evict_tiles would take any tile now (a caller publishing the map must cut it before they go)."""
    return len(vo.map.far_tile_rows(center_xy, radius_m, tile_m)) > 0


def restore_tiles(vo: OccVO, blocks: dict[Tile, dict[str, np.ndarray]]) -> int:
    """Put evicted tiles back (as evict_tiles returned them), moved by the loops closed since they were taken;
    returns the voxels restored."""
    t = len(vo.poses)
    restored = sum(vo.map.put(vo.loop_closure.corrected_block(block), t) for block in blocks.values())
    vo.loop_closure.drop_followed_voxels(t - 1, restored=True)  # taken before they came of age: as if never taken
    return restored


def tiles_near(cold: Iterable[Tile], ego_xy, radius_m: float, tile_m: float) -> list[Tile]:
    """Cold tiles to bring back: those within radius_m - tile_m of the ego, in tile order (the order they come back
    in is the map's row order, so it must not depend on how the caller's index was built, e.g. by a resume)."""
    keys = sorted(cold)
    if not keys:
        return []
    near = tile_distance(np.array(keys, np.int64), ego_xy, tile_m) <= radius_m - tile_m
    return [k for k, n in zip(keys, near) if n]


def tiles_reached(cold: Iterable[Tile], points: np.ndarray, pose: np.ndarray, tile_m: float) -> list[Tile]:
    """Cold tiles the frame's points land in at `pose`, or within REACH_MARGIN_M of them. Only when the working
    radius less a tile is below a frame's reach (~57 m); a bounding-box test first keeps it cheap otherwise. In tile
    order, as tiles_near."""
    margin = REACH_MARGIN_M
    xy = points @ pose[:2, :3].T + pose[:2, 3]
    lo = np.floor((xy.min(axis=0) - margin) / tile_m)
    hi = np.floor((xy.max(axis=0) + margin) / tile_m)
    candidates = sorted(k for k in cold if lo[0] <= k[0] <= hi[0] and lo[1] <= k[1] <= hi[1])
    if not candidates:
        return []
    ids = np.concatenate(
        [
            np.floor((xy + d) / tile_m).astype(np.int64)
            for d in ((0, 0), (-margin, -margin), (-margin, margin), (margin, -margin), (margin, margin))
        ]
    )
    packed = set(np.unique(pack_tiles(ids)).tolist())
    return [k for k, code in zip(candidates, pack_tiles(np.array(candidates, np.int64)).tolist()) if code in packed]
