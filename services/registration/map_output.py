"""A session's map output: the part of the working map a frame changed, cut into tiles and sent as MapUpdate
messages (split to fit max_message_bytes), at most every map_coalesce_s while frames wait."""

from __future__ import annotations

import hashlib
import logging
import time

import numpy as np

from occvo_core.map_tiles import changed_tiles, retile_region
from occvo_core.working_map import changed_map
from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_schemas.models import Array, MapTile, MapUpdate
from occvo_services.telemetry import log_event


def _tile_digest(tile) -> bytes:
    p, l = tile
    return hashlib.blake2b(
        np.ascontiguousarray(p).tobytes() + np.ascontiguousarray(l).tobytes(), digest_size=16
    ).digest()


def map_update(stream: str, seq: int, reset: bool, tile_m: float, tiles: dict) -> MapUpdate:
    """The MapUpdate of {(ix, iy): (points, labels)}, tiles in key order (each tile checked once: pydantic would
    check them all again as the update's field)."""
    checked = [
        MapTile(
            stream=stream,
            ix=ix,
            iy=iy,
            tile_m=tile_m,
            seq=seq,
            points=Array.from_numpy(np.asarray(p, np.float64)),
            labels=Array.from_numpy(np.asarray(l, np.uint8)),
        )
        for (ix, iy), (p, l) in sorted(tiles.items())
    ]
    return MapUpdate(stream=stream, seq=seq, reset=reset, tile_m=tile_m).model_copy(update={"tiles": checked})


class MapOutput:
    """The tiles a session has published, and when its map is cut for the next ones."""

    def __init__(self, stream: str, config, stats, log, put, report_error):
        self.stream, self.config, self.stats, self.log = stream, config, stats, log
        self.put, self.report_error = put, report_error
        self.cut_at = -np.inf  # time.monotonic() of the last cut
        self.pending = False  # the map changed since that cut (its tiles go out with a later frame's)
        self.extract_ms = self.tiling_ms = 0.0
        self.reset()

    def reset(self, send_all: bool = False) -> None:
        """Nothing published (a new trajectory, a closed session); send_all: a resume's next cut sends every tile."""
        self.tiles: dict = {}  # published tiles of the working map
        self.cold_digest: dict[tuple[int, int], bytes] = {}  # published content of an evicted tile
        self.send_all = send_all  # after a resume: the map service may lack the last frames' tiles

    def due(self, frames_waiting: bool) -> bool:
        """Whether the map is cut for tiles now: every frame of a stream caught up, while frames wait behind it (each
        update re-sends whole tiles) at most every map_coalesce_s, and after a resume at once."""
        period = self.config.map_coalesce_s
        if self.send_all or period <= 0 or time.monotonic() - self.cut_at >= period:
            return True
        return not frames_waiting

    def cut(self, vo) -> tuple:
        """The map changed since the last cut, copied (occvo_core.working_map.changed_map)."""
        t0 = time.perf_counter()
        self.cut_at, self.pending = time.monotonic(), False
        cut = changed_map(vo, self.config.tile_m)
        self.extract_ms = (time.perf_counter() - t0) * 1000.0
        return cut

    def hold(self) -> None:
        """The map's change waits for a later frame's cut (returns no cut)."""
        self.pending, self.extract_ms = True, 0.0

    def send(self, seq: int, restart: bool, cut, evicted, restored) -> None:
        """In the session's map thread: one frame's tiles cut and sent, in frame order."""
        try:
            t0 = time.perf_counter()
            sent = self.publish(seq, restart, cut, evicted, restored)
            self.stats.observe("map_publish", (time.perf_counter() - t0) * 1000.0 - (self.tiling_ms - self.extract_ms))
            self.stats.observe("tiling", self.tiling_ms)
            self.stats.observe("map_update", (time.perf_counter() - t0) * 1000.0 + self.extract_ms)
            if sent[0]:
                self.stats.inc("tiles_sent", sent[0])
        except Exception as exc:  # noqa: BLE001 - a worker never dies of one frame's tiles
            message = f"map update of seq {seq}: {type(exc).__name__}: {exc}"
            self.report_error(self.stream, "internal", message, seq=seq)
            log_event(self.log, "stage failed", logging.ERROR, stream=self.stream, error=repr(exc))

    def publish(self, seq: int, restart: bool, cut: tuple, evicted: dict, restored: list) -> tuple[int, int]:
        """Changed tiles of the working map as it was before this frame's eviction (an evicted tile goes out with its
        last content, then is not sent as emptied: the map service keeps it); a restored tile only if it changed.
        Returns (tiles sent, bytes sent)."""
        t0 = time.perf_counter()
        region, points, labels = cut
        tiles, dirty = retile_region(self.tiles, lambda *_: (points, labels), region, self.config.tile_m)
        self.tiling_ms = self.extract_ms + (time.perf_counter() - t0) * 1000.0
        if restart or self.send_all:
            changed = dict(tiles)
        else:
            changed = changed_tiles(
                {k: self.tiles[k] for k in dirty if k in self.tiles}, {k: tiles[k] for k in dirty if k in tiles}
            )
            for k in restored:
                was = self.cold_digest.pop(k, None)
                if k in changed and was is not None and _tile_digest(changed[k]) == was:
                    del changed[k]
        for k in evicted:
            if k in tiles:
                self.cold_digest[k] = _tile_digest(tiles[k])
        self.send_all = False
        self.tiles = {k: v for k, v in tiles.items() if k not in evicted} if evicted else tiles
        update = map_update(self.stream, seq, restart, self.config.tile_m, changed)
        return len(update.tiles), self._put_update(update)

    def _put_update(self, update: MapUpdate) -> int:
        """Publish a map update; one over max_message_bytes goes as several (the transport drops bigger messages),
        the reset with the first. Returns the bytes sent."""
        data = encode(update, 1 << 30)
        if len(data) > self.config.max_message_bytes and len(update.tiles) > 1:
            half = len(update.tiles) // 2
            first = update.model_copy(update={"tiles": update.tiles[:half]})
            return self._put_update(first) + self._put_update(
                update.model_copy(update={"tiles": update.tiles[half:], "reset": False})
            )
        self.put(keys.map_updates(self.stream), data)
        return len(data)
