"""Cut the semantic map into square x-y tiles for serving: tile (ix, iy) = (floor(x / tile_m), floor(y / tile_m))."""

from __future__ import annotations

import numpy as np

DEFAULT_TILE_M = 20.0


def tile_keys(points: np.ndarray, tile_m: float = DEFAULT_TILE_M) -> np.ndarray:
    """(N,2) int64 tile indices of world points (N,3)."""
    if tile_m <= 0:
        raise ValueError(f"tile size must be positive, got {tile_m}")
    return np.floor(np.asarray(points, dtype=np.float64)[:, :2] / tile_m).astype(np.int64)


def pack_tiles(tiles: np.ndarray) -> np.ndarray:
    """One int64 per (ix, iy) row, so grouping tiles is a 1-d sort, not a row-wise unique (~50x faster)."""
    tiles = np.asarray(tiles, dtype=np.int64)
    return (tiles[:, 0] << 32) + (tiles[:, 1] & 0xFFFFFFFF)


def tile_distance(tiles: np.ndarray, xy, tile_m: float) -> np.ndarray:
    """Distance from xy to the nearest point of each (ix, iy) tile's square (0 inside)."""
    lo = np.asarray(tiles, dtype=np.float64) * tile_m
    xy = np.asarray(xy, dtype=np.float64)[:2]
    d = np.maximum(np.maximum(lo - xy, 0.0), xy - (lo + tile_m))
    return np.hypot(d[:, 0], d[:, 1])


def tiles_from_map(
    points: np.ndarray, labels: np.ndarray, tile_m: float = DEFAULT_TILE_M
) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """Map (points (M,3), labels (M,)) -> {(ix, iy): (points, labels)}; each tile keeps the map's point order."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    labels = np.asarray(labels, dtype=np.uint8).reshape(-1)
    if len(points) != len(labels):
        raise ValueError(f"{len(points)} points but {len(labels)} labels")
    if len(points) == 0:
        return {}
    keys = tile_keys(points, tile_m)
    packed = pack_tiles(keys)
    order = np.argsort(packed, kind="stable")  # stable: point order inside a tile is the map's
    sorted_keys = packed[order]
    starts = np.flatnonzero(np.r_[True, sorted_keys[1:] != sorted_keys[:-1]])
    ends = np.r_[starts[1:], len(order)]
    out = {}
    for s, e in zip(starts, ends):
        first = order[s]
        sel = order[s:e]
        out[(int(keys[first, 0]), int(keys[first, 1]))] = (points[sel], labels[sel])
    return out


def retile_region(
    tiles: dict, map_points, region: np.ndarray | None, tile_m: float = DEFAULT_TILE_M
) -> tuple[dict, set]:
    """`tiles` (an earlier tiles_from_map of the map) brought up to date after a change confined to `region` (x-y box
    xmin, ymin, xmax, ymax; None = anywhere): the tiles the box overlaps are cut again, the others kept. map_points()
    gives the whole map, map_points((lo, hi, tile_m)) the points in tiles lo..hi (as OccVO.map_points). Returns
    (tiles, keys of the tiles cut again). Equals tiles_from_map(*map_points()) when nothing outside the region
    changed, at the cost of the changed part."""
    if region is None:
        new = tiles_from_map(*map_points(), tile_m)
        return new, set(new) | set(tiles)
    if region[0] > region[2]:
        return dict(tiles), set()
    lo = np.floor(np.asarray(region[:2]) / tile_m).astype(np.int64)
    hi = np.floor(np.asarray(region[2:]) / tile_m).astype(np.int64)
    redone = tiles_from_map(*map_points((lo, hi, tile_m)), tile_m)
    stale = {k for k in tiles if lo[0] <= k[0] <= hi[0] and lo[1] <= k[1] <= hi[1]}
    out = {k: v for k, v in tiles.items() if k not in stale}
    out.update(redone)
    return out, stale | set(redone)


def changed_tiles(old: dict, new: dict) -> dict[tuple[int, int], tuple[np.ndarray, np.ndarray]]:
    """Tiles of `new` that differ from `old`, plus tiles that disappeared (as empty arrays)."""
    out = {}
    for key, (p, l) in new.items():
        prev = old.get(key)
        if prev is None or not (np.array_equal(prev[0], p) and np.array_equal(prev[1], l)):
            out[key] = (p, l)
    for key in old.keys() - new.keys():
        out[key] = (np.zeros((0, 3)), np.zeros(0, np.uint8))
    return out
