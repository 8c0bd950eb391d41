"""The map's rows: one array per voxel field, grown by doubling, compacted when dropped voxels pile up, saved and
paged out whole. VoxelPFilterMap (voxel_map.py) gives the rows their meaning."""

from __future__ import annotations

import numpy as np

from occvo_core.grid import NUM_CLASSES
from occvo_core.map_tiles import pack_tiles
from occvo_core.registration.kernels import map_rows, row_blocks

_FIELDS = (
    "keys",
    "pos",
    "cov",
    "counts",
    "label",
    "t0",
    "f",
    "last",
    "wacc",
    "alive",
    "born",
    "in_window",
    "returning",
    "between",
)


def _field(arrays: dict, name: str) -> np.ndarray:
    """A saved state's or evicted block's array of a field. Saved before `born` or `in_window` existed: a voxel's t0
    is the best guess of its birth, its last sighting of its last frame in a registration window; before `returning`
    and `between`: 0."""
    if name in arrays:
        return np.asarray(arrays[name])
    if name == "counts" and "counts.at" in arrays:  # stored_rows' form: the nonzero entries
        counts = np.zeros((len(arrays["keys"]), NUM_CLASSES), np.int32)
        counts.reshape(-1)[np.asarray(arrays["counts.at"])] = arrays["counts.values"]
        return counts
    if name in ("returning", "between"):
        return np.zeros(len(arrays["keys"]), np.bool_ if name == "returning" else np.int32)
    return np.asarray(arrays[{"born": "t0", "in_window": "last"}.get(name, name)])


def stored_rows(rows: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Rows (state()'s) in the form a store keeps, a third smaller and read back by load_state as they were: the
    class counts as their nonzero entries (a voxel counts one class or two of 18) and the cell keys as int32 where
    they fit (a map within 850 km of its origin at 0.4 m)."""
    out = dict(rows)
    counts = np.ascontiguousarray(rows["counts"])
    if counts.size < 1 << 32:
        del out["counts"]
        out["counts.at"], out["counts.values"] = map_rows.nonzero_entries(counts)
    keys = rows["keys"]
    if len(keys) and keys.min() >= np.iinfo(np.int32).min and keys.max() <= np.iinfo(np.int32).max:
        out["keys"] = keys.astype(np.int32)
    return out


def _row_bytes(a: np.ndarray) -> np.ndarray:
    """A C-contiguous array as (rows, bytes per row) uint8, no copy."""
    return a.reshape(len(a), -1).view(np.uint8)


def copied(a: np.ndarray) -> np.ndarray:
    """A copy of an array, made without holding the GIL when it is big and C-contiguous (np.array holds it)."""
    a = np.asarray(a)
    if a.ndim == 0 or a.nbytes < (1 << 20) or not a.flags.c_contiguous:
        return np.array(a)
    out = np.empty_like(a)
    map_rows.copy_row_bytes(_row_bytes(out), _row_bytes(a), len(a))
    return out


class VoxelRows:
    """Voxel rows of `voxel` metres: rows keep their numbers until compact(); `alive` marks the voxels in the map."""

    def __init__(self, voxel_m: float):
        self.voxel = float(voxel_m)
        self._n = 0
        self._changed: np.ndarray | None = None  # x-y box of what changed since pop_changed_region(); None = anything
        self._alloc(1 << 16)

    def _alloc(self, capacity: int) -> None:
        old = getattr(self, "pos", None)
        spec = {
            "keys": ((capacity, 3), np.int64, 0),
            "pos": ((capacity, 3), np.float64, 0.0),
            "cov": ((capacity, 3, 3), np.float64, 0.0),
            "counts": ((capacity, NUM_CLASSES), np.int32, 0),
            "label": ((capacity,), np.uint8, 0),
            "t0": ((capacity,), np.int32, 0),
            "f": ((capacity,), np.int32, 0),
            "last": ((capacity,), np.int32, -1),
            "wacc": ((capacity,), np.float64, 0.0),
            "alive": ((capacity,), np.bool_, False),
            "born": ((capacity,), np.int32, 0),  # frame the voxel was made: unlike t0, not shifted by put()
            "in_window": ((capacity,), np.int32, 0),  # last frame whose registration window held it (enter())
            "returning": ((capacity,), np.bool_, False),  # back in the window after frames away, not seen again yet
            "between": ((capacity,), np.int32, 0),  # frames in view between two visits: the served map skips them
        }
        for name, (shape, dtype, fill) in spec.items():
            # zeros come from calloc: pages cost nothing until touched, so doubling does not write the new half
            arr = np.zeros(shape, dtype) if fill == 0 else np.full(shape, fill, dtype)
            if old is not None:
                map_rows.copy_row_bytes(_row_bytes(arr), _row_bytes(getattr(self, name)), self._n)
            setattr(self, name, arr)
        blocks = -(-capacity // row_blocks.BLOCK_ROWS)
        self.block_lo, self.block_hi = np.empty((blocks, 3), np.int64), np.empty((blocks, 3), np.int64)
        self._bound_rows_from(0)

    def _bound_rows_from(self, row: int) -> None:
        """Recompute the key boxes of the row blocks (row_blocks) from the one holding `row` on: rows from there on
        were made or renumbered."""
        row_blocks.block_bounds(self.keys, self._n, row // row_blocks.BLOCK_ROWS, self.block_lo, self.block_hi)

    def __len__(self) -> int:
        return int(np.count_nonzero(self.alive[: self._n]))

    def _touch(self, pos: np.ndarray) -> None:
        if len(pos):
            self._touch_box(np.concatenate([pos[:, :2].min(axis=0), pos[:, :2].max(axis=0)]))

    def _touch_box(self, box: np.ndarray) -> None:
        if self._changed is not None:
            self._changed[:2] = np.minimum(self._changed[:2], box[:2])
            self._changed[2:] = np.maximum(self._changed[2:], box[2:])

    def pop_changed_region(self) -> np.ndarray | None:
        """(xmin, ymin, xmax, ymax) holding, before and after, every voxel whose position, label, persistence or
        presence changed since the last call (empty box: none; None: anything, e.g. after a reset or load). Lets a
        caller re-tile only that part of the map. Voxels handed out by take() are not included: the caller has them."""
        out = self._changed
        self._changed = np.array([np.inf, np.inf, -np.inf, -np.inf])
        return out

    def remove(self, rows: np.ndarray) -> None:
        """Drop voxels (the dynamic object filter's moved objects). Rows keep their numbers until compact()."""
        self._touch(self.pos[rows])
        self.alive[rows] = False

    def compact(self, min_dead_share: float = 1 / 3, headroom: float = 1 / 8, min_reclaim: float = 1 / 32) -> None:
        """Reclaim the space of dropped voxels once they are a given share of the rows, or once the rows come within
        `headroom` of the capacity: reclaiming them beats doubling every array. Near the capacity only when at least
        `min_reclaim` of it comes back, or a map full of live rows would copy itself whole for a few dead ones at
        every frame. Renumbers rows, keeping their order."""
        n = self._n
        dead = n - np.count_nonzero(self.alive[:n])  # no inverted copy of the map's flags
        near_full = n > (1 - headroom) * len(self.pos) and dead >= min_reclaim * len(self.pos)
        if dead == 0 or (dead <= n * min_dead_share and not near_full):
            return
        keep = np.flatnonzero(self.alive[:n])
        for name in _FIELDS:
            map_rows.gather_row_bytes(_row_bytes(getattr(self, name)), keep)
        self.alive[len(keep) : n] = False
        self._n = len(keep)
        self._bound_rows_from(0)

    def state(self, copy: bool = True) -> dict[str, np.ndarray]:
        """Every row (dropped ones too, so row order and thus tie-breaking survive a reload); copy=False: views."""
        return {
            name: copied(getattr(self, name)[: self._n]) if copy else getattr(self, name)[: self._n] for name in _FIELDS
        }

    def load_state(self, state: dict[str, np.ndarray]) -> None:
        n = len(state["keys"])
        self._n = 0
        self._changed = None
        self._alloc(max(1 << 16, n))
        for name in _FIELDS:
            getattr(self, name)[:n] = _field(state, name)
        self._n = n
        self._bound_rows_from(0)

    def tile_ids(self, tile_m: float, rows: np.ndarray | None = None) -> np.ndarray:
        """(n,2) x-y tile of every row (or of `rows`): floor(pos / tile_m), as occvo_core.map_tiles cuts the map."""
        pos = self.pos[: self._n] if rows is None else self.pos[rows]
        return np.floor(pos[:, :2] / tile_m).astype(np.int64)

    def resident_tiles(self, tile_m: float) -> set[tuple[int, int]]:
        """Tiles with live voxels."""
        tiles = self.tile_ids(tile_m)[self.alive[: self._n]]
        if not len(tiles):
            return set()
        _, first = np.unique(pack_tiles(tiles), return_index=True)
        return {(int(a), int(b)) for a, b in tiles[first]}

    def take(self, rows: np.ndarray, t: int) -> dict[str, np.ndarray]:
        """Remove live rows and return their voxels with everything the voxel pfilter knows of them."""
        block = {name: getattr(self, name)[rows].copy() for name in _FIELDS if name != "alive"}
        block["taken_at"] = np.array(t, np.int64)
        self.alive[rows] = False
        return block

    def far_tile_rows(self, center_xy, radius_m: float, tile_m: float) -> np.ndarray:
        """Live rows, ascending, of the tiles whose square lies wholly farther than radius_m from center_xy."""
        center = np.asarray(center_xy, np.float64)
        return map_rows.far_tile_rows(
            self.pos, self.alive, self._n, center[0], center[1], float(tile_m), float(radius_m)
        )

    def take_far_tiles(self, center_xy, radius_m: float, tile_m: float, t: int) -> dict[tuple[int, int], dict]:
        """take() every tile whose square lies wholly farther than radius_m from center_xy: {tile: its voxels}."""
        rows = self.far_tile_rows(center_xy, radius_m, tile_m)
        if len(rows) == 0:
            return {}
        tiles = self.tile_ids(tile_m, rows)
        _, first, inverse = np.unique(pack_tiles(tiles), return_index=True, return_inverse=True)
        uniq = tiles[first]
        inverse = inverse.reshape(-1)
        order = np.argsort(inverse, kind="stable")
        bounds = np.searchsorted(inverse[order], np.arange(len(uniq) + 1))
        out = {
            (int(uniq[u, 0]), int(uniq[u, 1])): self.take(rows[order[bounds[u] : bounds[u + 1]]], t)
            for u in range(len(uniq))
        }
        self.compact()
        return out

    def live_rows(
        self, born_after: int | None = None, born_at: int | None = None, born_up_to: int | None = None
    ) -> np.ndarray:
        """Live rows, ascending, of the voxels made after, at or up to a frame (loop closure's map correction)."""
        n = self._n
        keep = self.alive[:n].copy()
        for bound, test in ((born_after, np.greater), (born_at, np.equal), (born_up_to, np.less_equal)):
            if bound is not None:
                keep &= test(self.born[:n], bound)
        return np.flatnonzero(keep)

    def born_of(self, rows: np.ndarray) -> np.ndarray:
        """Frame each row's voxel was made."""
        return self.born[rows]
