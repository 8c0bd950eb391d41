"""Paging of the bounded working map: tiles wholly beyond working_radius_m go to the store, and come back when the ego
is near them again or a frame reaches into them (occvo_core.working_map)."""

from __future__ import annotations

import time

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_core.working_map import changed_map, has_far_tiles, tiles_near, tiles_reached
from occvo_services.array_pack import unpack_arrays
from occvo_services.registration.state import StreamState

MIN_SAFE_RADIUS_M = 60.0  # a frame reaches ~57 m (the grid's corners): eviction closer than that changes registration


class Paging:
    """RegistrationWorker's step after a pose and its working-map paging calls."""

    def _advance(self, stream: str, st: StreamState, frame: OccupancyFrame, seq: int, publish: bool):
        """A whole frame as a live one goes (register, then _finish); a resume's replay of the journal uses it, so it
        reproduces the poses."""
        return self._finish(stream, st, st.vo.register(frame), frame, seq, publish)

    def _finish(
        self, stream: str, st: StreamState, reg, frame: OccupancyFrame, seq: int, publish: bool | None, entered: int = 0
    ):
        """After the pose: loop closure and map update (OccVO.complete), keep every tile wholly resident or wholly
        cold, evict far map, and bring back the cold map near the new pose, which the next frame registers against.
        Returns (result, tiles restored, evicted blocks, the changed part of the map before eviction if publish:
        what _publish_map cuts into tiles). publish None: when _map_due (the frame that entered the lane as `entered`)
        or tiles come back or leave now (their content goes out with this frame's); else the change waits for a later
        frame's cut."""
        t_complete = time.perf_counter()
        result = self._kernels(st.vo, None, st.vo.complete, reg)  # the next frame's prepare waits for it (lane)
        pose = np.asarray(result.pose, float)
        t0 = time.perf_counter()
        st.complete_ms = (t0 - t_complete) * 1000.0
        restored = list(st.restored_for_next)
        if st.cold:  # a frame that reached into an evicted tile: bring the rest back, so the tile stays whole
            restored += self._restore(stream, st, self._reached(st, frame, pose))
        t_map = time.perf_counter()
        cut = None
        if publish is None:
            publish = bool(restored) or self._map_due(stream, st, entered) or self._evicts(st, pose)
            st.map_pending = not publish
        if publish:  # only the part of the map changed since the last cut is cut again (a replay leaves it open)
            cut = self._cut(st)  # copied: cut and sent beside the next registration
        st.extract_ms = (time.perf_counter() - t_map) * 1000.0
        t_evict = time.perf_counter()
        evicted = self._evict_far(st, seq, pose)
        st.evict_ms = (time.perf_counter() - t_evict) * 1000.0
        st.ego_xy = pose[:2, 3].copy()
        t_near = time.perf_counter()
        # published with the next frame's tiles (they are cut then); committed with this frame
        st.restored_for_next = self._restore(stream, st, self._near(st))
        st.restore_ms = (t_map - t0 + time.perf_counter() - t_near) * 1000.0
        return result, restored, evicted, cut

    def _cut(self, st: StreamState) -> tuple:
        """The map changed since the last cut, copied (occvo_core.working_map.changed_map)."""
        st.map_cut_at, st.map_pending = time.monotonic(), False
        return changed_map(st.vo, self.config.tile_m)

    def _map_due(self, stream: str, st: StreamState, entered: int) -> bool:
        """Whether the map is cut for tiles now: every frame of a stream caught up, while frames wait behind it (each
        update re-sends whole tiles) at most every map_coalesce_s, and after a resume at once."""
        period = self.config.map_coalesce_s
        if st.send_all_tiles or period <= 0 or time.monotonic() - st.map_cut_at >= period:
            return True
        return not self._frames_waiting(stream, st, entered)

    def _frames_waiting(self, stream: str, st: StreamState, entered: int) -> bool:
        """Whether a frame of the stream came after the one that entered the lane as `entered`."""
        return st.entered != entered or self._queued(stream)

    def _flush_map(self, stream: str, st: StreamState) -> None:
        """In the after-pose thread: the tiles held back for a frame that did not come (refused, or none followed)."""
        if st.map_pending and st.vo is not None and st.seqs and st.map_thread is not None:
            cut = self._cut(st)
            self._map_done(st)
            st.map_tail = st.map_thread.submit(self._send_tiles, stream, st, st.seqs[-1], False, cut, {}, [])

    def _evicts(self, st: StreamState, pose: np.ndarray) -> bool:
        """Whether _evict_far takes any tile at this pose."""
        radius = self.config.working_radius_m
        return radius is not None and has_far_tiles(st.vo, pose[:2, 3], radius, self.config.tile_m)

    def _reached(self, st: StreamState, frame: OccupancyFrame, pose: np.ndarray) -> list[tuple[int, int]]:
        """Cold tiles the frame's points reach at `pose` (occvo_core.working_map.tiles_reached)."""
        return tiles_reached(st.cold, frame.points, pose, self.config.tile_m)

    def _near(self, st: StreamState) -> list[tuple[int, int]]:
        """Cold tiles near the last pose to bring back (occvo_core.working_map.tiles_near)."""
        radius = self.config.working_radius_m
        if radius is None or not st.cold:
            return []
        return tiles_near(st.cold, st.ego_xy, radius, self.config.tile_m)

    def _restore(self, stream: str, st: StreamState, back: list[tuple[int, int]]) -> list[tuple[int, int]]:
        """Put cold tiles back into the working map (newest block first: put() keeps a cell's newer voxel)."""
        for k in back:
            seqs = st.cold.pop(k)
            for e in sorted(seqs, reverse=True):
                st.vo.restore_tiles({k: unpack_arrays(self.store.cold_block(stream, k[0], k[1], e))})
                st.pending_restored.append((k[0], k[1], e))
        if back:
            self.stats.inc("tiles_restored", len(back))
        return list(back)

    def _evict_far(self, st: StreamState, seq: int, pose: np.ndarray) -> dict:
        """After a step: take the tiles wholly farther than working_radius_m out of the working map."""
        if self.config.working_radius_m is None:
            return {}
        blocks = st.vo.evict_tiles(pose[:2, 3], self.config.working_radius_m, self.config.tile_m)
        for k in blocks:
            st.cold.setdefault(k, []).append(seq)
        if blocks:
            self.stats.inc("tiles_evicted", len(blocks))
        return blocks
