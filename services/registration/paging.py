"""Paging of a session's bounded working map: tiles wholly beyond working_radius_m go to the store, and come back
when the ego is near them again or a frame reaches into them (occvo_core.working_map)."""

from __future__ import annotations

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_core.registration.voxel_rows import stored_rows
from occvo_core.working_map import has_far_tiles, tiles_near, tiles_reached
from occvo_services.array_pack import unpack_arrays

MIN_SAFE_RADIUS_M = 60.0  # a frame reaches ~57 m (the grid's corners): eviction closer than that changes registration


class Pager:
    """What a session keeps of its evicted map: which tiles are cold (and the frames they were evicted at: their
    store rows), the restores not yet stored, and the ego position paging is centred on."""

    def __init__(self, stream: str, store, stats, radius_m: float | None, tile_m: float):
        self.stream, self.store, self.stats = stream, store, stats
        self.radius_m, self.tile_m = radius_m, tile_m
        self.reset()

    def reset(self, cold: dict | None = None, ego_xy: np.ndarray | None = None) -> None:
        self.cold: dict[tuple[int, int], list[int]] = cold or {}  # evicted tile -> seqs it was evicted at
        self.pending_restored: list[tuple[int, int, int]] = []  # restored, not yet stored (finish_frame)
        self.restored_for_next: list[tuple[int, int]] = []  # restored after the last frame, not yet published
        self.ego_xy = ego_xy  # x-y of the last registered pose (eviction and restore centre)

    def moved_to(self, pose: np.ndarray) -> None:
        """The ego's new position: eviction and restores centre on it."""
        self.ego_xy = pose[:2, 3].copy()

    def restore_near(self, vo) -> None:
        """The cold tiles near the ego back in the working map; published with the next frame's tiles."""
        self.restored_for_next = self.restore(vo, self.near())

    def restores_stored(self) -> None:
        """The restores so far are in the store (finish_frame), or a replay's (the store had them)."""
        self.pending_restored = []

    def adopt_cold(self, cold: dict) -> None:
        """The store's cold index replaces this one (a resume that ended with another)."""
        self.cold = cold

    def reached(self, frame: OccupancyFrame, pose: np.ndarray) -> list[tuple[int, int]]:
        """Cold tiles the frame's points reach at `pose` (occvo_core.working_map.tiles_reached)."""
        return tiles_reached(self.cold, frame.points, pose, self.tile_m) if self.cold else []

    def near(self) -> list[tuple[int, int]]:
        """Cold tiles near the last pose to bring back (occvo_core.working_map.tiles_near)."""
        if self.radius_m is None or not self.cold:
            return []
        return tiles_near(self.cold, self.ego_xy, self.radius_m, self.tile_m)

    def restore(self, vo, back: list[tuple[int, int]]) -> list[tuple[int, int]]:
        """Put cold tiles back into the working map (newest block first: put() keeps a cell's newer voxel)."""
        for k in back:
            seqs = self.cold.pop(k)
            for e in sorted(seqs, reverse=True):
                vo.restore_tiles({k: unpack_arrays(self.store.cold_block(self.stream, k[0], k[1], e))})
                self.pending_restored.append((k[0], k[1], e))
        if back:
            self.stats.inc("tiles_restored", len(back))
        return list(back)

    def evicts(self, vo, pose: np.ndarray) -> bool:
        """Whether evict_far takes any tile at this pose."""
        return self.radius_m is not None and has_far_tiles(vo, pose[:2, 3], self.radius_m, self.tile_m)

    def evict_far(self, vo, seq: int, pose: np.ndarray) -> dict:
        """After a step: take the tiles wholly farther than working_radius_m out of the working map, in the form a
        store keeps (voxel_rows.stored_rows)."""
        if self.radius_m is None:
            return {}
        blocks = {k: stored_rows(b) for k, b in vo.evict_tiles(pose[:2, 3], self.radius_m, self.tile_m).items()}
        for k in blocks:
            self.cold.setdefault(k, []).append(seq)
        if blocks:
            self.stats.inc("tiles_evicted", len(blocks))
        return blocks
