"""The global semantic map with the Voxel PFilter: per voxel, t0 (first frame seen) and f (frames seen);
p-index = f / (t - t0) at frame t (voxel_pfilter.p_index); only voxels with p-index above the threshold constrain
registration."""

from __future__ import annotations

import numba
import numpy as np

from occvo_core.registration.kernels import map_rows, map_window, nearest, row_blocks
from occvo_core.registration.kernels import voxel_pfilter as pfilter_kernels
from occvo_core.registration.local_map import EgoMap, LocalMap, moved  # noqa: F401 - EgoMap, moved: older import path
from occvo_core.registration.voxel_pfilter import p_index
from occvo_core.registration.voxel_rows import _FIELDS, VoxelRows, _field, _row_bytes, copied  # noqa: F401


class VoxelPFilterMap(VoxelRows):
    def __init__(
        self,
        voxel_m: float = 0.4,
        p_index_threshold: float = 0.5,
        pfilter: bool = True,
        merge_radius_m: float | None = None,
        observe_radius_m: float = 0.0,
    ):
        self.p_index_threshold = float(p_index_threshold)
        self.pfilter = pfilter
        self.merge_radius = 0.5 * float(voxel_m) if merge_radius_m is None else float(merge_radius_m)
        self.observe_radius = float(observe_radius_m)
        super().__init__(voxel_m)

    def p_index(self, t: int) -> np.ndarray:
        """p-index of every row at frame t (f counts frames before t; t0 < t for every existing voxel)."""
        n = self._n
        return p_index(self.f[:n], t - self.t0[:n])

    def window(self, lower: np.ndarray, upper: np.ndarray, t: int | None = None, tight: bool = False) -> LocalMap:
        """Every live voxel with key in [lower, upper]; `usable` marks those with p-index above the threshold at
        frame t (all of them with the filter off or no t). tight: the grid spans only the voxels found, not the
        whole box (a wide, tall search box is mostly empty: its dense grid would cost tens of MB)."""
        origin, upper = np.asarray(lower, np.int64), np.asarray(upper, np.int64)
        if tight:
            lo, hi = map_window.key_bounds(self.keys, self.alive, self._n, self.block_lo, self.block_hi, origin, upper)
            origin, upper = (lo, hi) if np.all(lo <= hi) else (origin, origin)
        rows, pos, labels, p_index, grid = map_window.window_voxels(
            self.keys,
            self.alive,
            self.f,
            self.t0,
            self.pos,
            self.label,
            self._n,
            self.block_lo,
            self.block_hi,
            origin,
            upper,
            t if t is not None else 0,
        )
        usable = p_index > self.p_index_threshold if (t is not None and self.pfilter) else np.ones(len(rows), bool)
        return LocalMap(rows, pos, labels, p_index, usable, grid, origin, upper - origin + 1, self.voxel, self)

    def enter(self, local: LocalMap, t: int) -> tuple[np.ndarray, np.ndarray]:
        """Frame t's registration window: a voxel back in it after frames outside (a place driven away from and come
        back to, without eviction) has those frames taken out of its p-index, as put() does for evicted ones: the
        p-index counts the frames a voxel could be seen in. On a single pass no voxel leaves the window and comes
        back, and this changes nothing. Updates local's p-index and usable; returns (rows, frames away) for
        entered() to record once the frame is committed."""
        away, back = pfilter_kernels.window_gaps(local.rows, self.in_window, int(t))
        if len(back):
            r = local.rows[back]
            local.p_index[back] = p_index(self.f[r], t - (self.t0[r] + away[back]))
            if self.pfilter:
                local.usable[back] = local.p_index[back] > self.p_index_threshold
        return local.rows, away

    def entered(self, rows: np.ndarray, away: np.ndarray, t: int) -> None:
        """Record enter()'s window: t0 and the last sighting move on by the frames away (persistence, seen over the
        frames in view, stays as it was), and the window held them at frame t. Rows dropped since are skipped."""
        pfilter_kernels.record_window(
            rows, away, self.alive, self.t0, self.last, self.returning, self.in_window, np.int32(t)
        )

    def merge(
        self,
        points_world: np.ndarray,
        labels: np.ndarray,
        covs_world: np.ndarray,
        t: int,
        local: LocalMap | None = None,
        old_born_before: int | None = None,
        on_old: bool = False,
    ) -> np.ndarray:
        """Add frame t's points (world frame) and return the map rows they landed in (-1: dropped). `local`, when it
        covers the points, saves building the window again (its grid is used up: new voxels are written into it).
        With old_born_before, the persistent voxels made before that frame are an old map (loop closure):
        - a frame on it (on_old) neither moves them nor adds a voxel beside them: a point in an old voxel's cell, or
          within the observe radius of one in an empty cell, counts as a sighting of it and is dropped (the frame's
          pose came from that map: merging would feed each lap's registration error back into the map the next lap
          follows, and a revisit must not grow a second layer beside it); its other points make voxels as usual
          (the caller decides how long they live: OccVO drops them before they could be old map);
        - a frame off it leaves them as they are: not merged into, not counted as seen, and points in their cells
          are dropped (a frame that drifted would drag them and wear down their p-index by chance overlaps)."""
        keys, lo, hi = pfilter_kernels.voxel_keys(points_world, self.voxel)
        if local is None or not (np.all(lo >= local.origin) and np.all(hi < local.origin + local.dims)):
            local = self.window(lo - 1, hi + 1)
        alive, back, back_last = pfilter_kernels.window_rows_state(local.rows, self.alive, self.returning, self.last)
        # dropped points still count as sightings (not of frozen voxels)
        out, seen_from, seen_keys = None, points_world, keys
        old = self.persistent_rows(local.rows, old_born_before) if old_born_before is not None else None
        if old is not None and old.any():
            cells = local.cells(keys)
            held = local.grid[cells]
            if on_old:
                take = held < 0
                d, _ = local.nearest(points_world[take], int(np.ceil(self.observe_radius / self.voxel)), usable=old)
                take[take] = d > self.observe_radius
                take |= (held >= 0) & ~old[np.maximum(held, 0)]
            else:
                take = ~((held >= 0) & old[np.maximum(held, 0)])
                alive &= ~old
            out = np.full(len(keys), -1, np.int64)
            points_world, labels, covs_world, keys = points_world[take], labels[take], covs_world[take], keys[take]
        parts = numba.get_num_threads()
        # the sightings are read with the lookups, where the points are those seen from (none dropped)
        rows, first_key, seen = pfilter_kernels.assign_voxels(
            points_world,
            keys,
            local.pos,
            local.grid,
            local.origin,
            local.dims,
            self.merge_radius,
            local.rows,
            alive,
            self._n,
            self.observe_radius if out is None else 0.0,
            parts,
        )
        n_new = len(first_key)
        if self._n + n_new > len(self.pos):
            self._alloc(max(2 * len(self.pos), self._n + n_new))
        new = slice(self._n, self._n + n_new)
        self.keys[new] = keys[first_key]
        self.t0[new] = self.born[new] = self.in_window[new] = t
        self.returning[new] = False
        self.between[new] = 0
        self.f[new] = 0
        self.last[new] = -1
        self.counts[new] = 0
        self.alive[new] = True
        self._n += n_new
        self._bound_rows_from(new.start)
        changed = np.array([np.inf, np.inf, -np.inf, -np.inf])  # merged voxels before and after, observed ones
        pfilter_kernels.merge_points(
            rows,
            points_world,
            covs_world,
            labels,
            t,
            self.pos,
            self.cov,
            self.counts,
            self.label,
            self.t0,
            self.f,
            self.last,
            self.wacc,
            self.pfilter,
            changed,
            parts,
        )
        if self.observe_radius > 0:
            if out is not None:
                seen = pfilter_kernels.observe_points(
                    seen_from, seen_keys, local.pos, local.grid, local.origin, local.dims, self.observe_radius,
                    len(local.rows), parts,
                )  # fmt: skip
            pfilter_kernels.count_observed(
                seen, local.pos, local.rows, alive, self.f, self.last, self.in_window, np.int32(t), changed, parts
            )
        else:  # a voxel seen is in view, whatever window this frame registered in (count_observed does it too)
            pfilter_kernels.mark_in_window(local.rows, self.last, self.in_window, np.int32(t))
        self._touch_box(changed)
        # seen again after a visit away: the frames in view since its last sighting (leaving, then coming back)
        # lie between two visits, which the served map does not count, as it does not count those before a
        # voxel's first sighting (a place seen in glimpses fell out of the served map at every revisit)
        again = self.last[back] == t
        self.between[back[again]] += ((t - 1) - back_last[again]).astype(np.int32)
        self.returning[back[again]] = False
        if out is not None:
            out[take] = rows
            return out
        return rows

    def put(self, block: dict[str, np.ndarray], t: int) -> int:
        """Add back voxels taken at an earlier frame, as if last seen at frame t - 1: the frames a voxel spent out of
        view do not count against its p-index, which comes back as its share of the frames from its first to its
        last sighting (what persistent() judges). Without this, a place revisited after a loop would have no reliable
        voxels left and the odometry could not register to it. A voxel whose cell already holds a live voxel is
        dropped: the map observed there since is newer. Returns the number of voxels added."""
        keys = np.asarray(block["keys"], np.int64)
        if len(keys) == 0:
            return 0
        lower, upper = keys.min(axis=0), keys.max(axis=0)
        held = self.window(lower, upper)
        cells = held.cells(keys)
        new = held.grid[cells] < 0
        seen = np.asarray(block["last"], np.int64)[new]
        shift = (int(t) - 1) - np.where(seen >= 0, seen, int(block["taken_at"]) - 1)
        n_new = int(new.sum())
        if self._n + n_new > len(self.pos):
            self._alloc(max(2 * len(self.pos), self._n + n_new))
        rows = slice(self._n, self._n + n_new)
        for name in _FIELDS:
            if name != "alive":
                getattr(self, name)[rows] = _field(block, name)[new]
        self.t0[rows] += shift
        self.last[rows] = self.in_window[rows] = int(t) - 1
        self.returning[rows] = True
        self.alive[rows] = True
        self._touch(self.pos[rows])
        self._n += n_new
        self._bound_rows_from(rows.start)
        return n_new

    def move(
        self,
        rows: np.ndarray,
        rot: np.ndarray,
        trans: np.ndarray,
        ghost_radius_m: float = 0.0,
        born_before: int = 0,
        group: np.ndarray | None = None,
    ) -> int:
        """Move live rows rigidly, each by its own rotation (k,3,3) and translation (k,3) (or by those of its
        `group`, (k,) indices into rot and trans), as a loop closure corrects the map made since a place was last
        seen. A moved voxel is dropped when its new cell already holds a live voxel (the map seen there first
        stands, as in put()) or another moved voxel first in turn_before's order, or when it moved more than a voxel
        and a reliable voxel born before `born_before` with its label lies within ghost_radius_m: it is that voxel
        seen again through drift. Returns the number dropped."""
        rows = np.asarray(rows, np.int64)
        if len(rows) == 0:
            return 0
        group = np.arange(len(rows)) if group is None else np.asarray(group, np.int64)
        box = np.array([np.inf, np.inf, -np.inf, -np.inf])  # where they were and went: only that part is re-tiled
        moved_far = map_rows.move_rows(
            self.pos,
            self.cov,
            self.keys,
            rows,
            np.ascontiguousarray(rot, np.float64),
            np.ascontiguousarray(trans, np.float64),
            group,
            self.voxel,
            box,
        )
        self._touch_box(box)
        row_blocks.grow_blocks(self.keys, rows, self.block_lo, self.block_hi)
        keys = self.keys[rows]
        self.alive[rows] = False  # judge the moved voxels against the others
        held = self.window(keys.min(axis=0) - 1, keys.max(axis=0) + 1)
        keep = map_rows.claim_cells(self.keys, self.pos, rows, held.grid, held.origin, held.dims)
        if ghost_radius_m > 0 and len(held):
            old = self.persistent_rows(held.rows, born_before)
            judge = np.flatnonzero(keep & moved_far)  # a voxel moved less than its size was there already
            pos = self.pos[rows[judge]]
            near = nearest.near_any(
                pos, held.pos[old], ghost_radius_m
            )  # most of a lap is far from the old map: skip it
            judge, pos = judge[near], pos[near]
            d, j = held.nearest(pos, int(np.ceil(ghost_radius_m / self.voxel)), usable=old)
            ghost = (j >= 0) & (d <= ghost_radius_m)
            ghost[ghost] = held.labels[j[ghost]] == self.label[rows[judge[ghost]]]
            keep[judge[ghost]] = False
        self.alive[rows[keep]] = True
        return int(len(rows) - keep.sum())

    def persistent(self) -> np.ndarray:
        """The voxel pfilter on the finished map, per live row: seen in more than the threshold's share of the frames
        from its first to its last sighting (the p-index over the time it was in view; the plain p-index would also
        punish a voxel for every frame after the car drove past it), each visit's from its first to its last sighting
        there: the frames between two visits are skipped as the frames before the first sighting are."""
        return self.persistent_rows(slice(0, self._n), per_visit=True)

    def persistent_rows(
        self, rows: np.ndarray | slice, born_before: int | None = None, per_visit: bool = False
    ) -> np.ndarray:
        """persistent() for the given rows; by default loop closure's judge of the old map, over the whole span from
        the first to the last sighting (the frames between visits too: a voxel seen only in glimpses is no anchor);
        with born_before, only voxels made before that frame."""
        keep = self.alive[rows].copy()
        if self.pfilter:
            span = self.last[rows] - self.t0[rows] + 1 - (self.between[rows] if per_visit else 0)
            keep &= p_index(self.f[rows], span) > self.p_index_threshold
        if born_before is not None:
            keep &= self.born[rows] < born_before
        return keep

    def points(self, tiles: tuple[np.ndarray, np.ndarray, float] | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The map a user gets: the persistent voxels (all live voxels with the filter off); with tiles = (lo, hi,
        tile_m), those whose x-y tile floor(pos / tile_m) lies in lo..hi."""
        if tiles is not None:
            lo, hi, tile_m = tiles
            rows = pfilter_kernels.persistent_in_tiles(
                self.pos,
                self.alive,
                self.f,
                self.last,
                self.t0,
                self.between,
                self._n,
                self.p_index_threshold,
                self.pfilter,
                np.asarray(lo, np.int64),
                np.asarray(hi, np.int64),
                float(tile_m),
            )
            return self.pos[rows], self.label[rows]
        keep = self.persistent()
        return self.pos[: self._n][keep].copy(), self.label[: self._n][keep].copy()

    def arrays(self, t: int) -> dict[str, np.ndarray]:
        """Every live voxel: points, labels, t0, f, last seen, p-index at frame t, and `persistent` (in the map)."""
        n = self._n
        alive = self.alive[:n]
        return {
            "points": self.pos[:n][alive],
            "labels": self.label[:n][alive],
            "t0": self.t0[:n][alive],
            "f": self.f[:n][alive],
            "last_seen": self.last[:n][alive],
            "p_index": self.p_index(t)[alive],
            "persistent": self.persistent()[alive],
        }
