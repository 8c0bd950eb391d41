"""Map publishing: the tiles a frame changed, cut again and sent as MapUpdate messages (split to fit max_message_bytes)."""

from __future__ import annotations

import hashlib
import time

import numpy as np
import zenoh

from occvo_core.map_tiles import changed_tiles, retile_region
from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_schemas.models import Array, MapTile, MapUpdate
from occvo_services.registration.state import StreamState


def _tile_digest(tile) -> bytes:
    p, l = tile
    return hashlib.blake2b(
        np.ascontiguousarray(p).tobytes() + np.ascontiguousarray(l).tobytes(), digest_size=16
    ).digest()


def map_update(stream: str, seq: int, reset: bool, tile_m: float, tiles: dict) -> MapUpdate:
    """The MapUpdate of {(ix, iy): (points, labels)}, tiles in key order."""
    return MapUpdate(
        stream=stream,
        seq=seq,
        reset=reset,
        tile_m=tile_m,
        tiles=[
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
        ],
    )


class MapPublisher:
    """RegistrationWorker's map updates."""

    def _publish_map(
        self,
        stream: str,
        st: StreamState,
        seq: int,
        restart: bool,
        cut: tuple,
        evicted: dict,
        restored: list,
    ) -> tuple[int, int]:
        """Changed tiles of the working map as it was before this frame's eviction (an evicted tile goes out with its
        last content, then is not sent as emptied: the map service keeps it); a restored tile only if it changed.
        `cut`: occvo_core.working_map.changed_map's copy of the changed part. Returns (tiles sent, bytes sent)."""
        t0 = time.perf_counter()
        region, points, labels = cut
        tiles, dirty = retile_region(st.tiles, lambda *_: (points, labels), region, self.config.tile_m)
        st.tiling_ms = st.extract_ms + (time.perf_counter() - t0) * 1000.0
        if restart or st.send_all_tiles:
            changed = dict(tiles)
        else:
            changed = changed_tiles(
                {k: st.tiles[k] for k in dirty if k in st.tiles}, {k: tiles[k] for k in dirty if k in tiles}
            )
            for k in restored:
                was = st.cold_digest.pop(k, None)
                if k in changed and was is not None and _tile_digest(changed[k]) == was:
                    del changed[k]
        for k in evicted:
            if k in tiles:
                st.cold_digest[k] = _tile_digest(tiles[k])
        st.send_all_tiles = False
        st.tiles = {k: v for k, v in tiles.items() if k not in evicted} if evicted else tiles
        update = map_update(stream, seq, restart, self.config.tile_m, changed)
        return len(update.tiles), self._put_update(stream, update)

    def _put_update(self, stream: str, update: MapUpdate) -> int:
        """Publish a map update; one over max_message_bytes goes as several (the transport drops bigger messages),
        the reset with the first. Returns the bytes sent."""
        data = encode(update, 1 << 30)
        if len(data) > self.config.max_message_bytes and len(update.tiles) > 1:
            half = len(update.tiles) // 2
            return self._put_update(
                stream, update.model_copy(update={"tiles": update.tiles[:half]})
            ) + self._put_update(stream, update.model_copy(update={"tiles": update.tiles[half:], "reset": False}))
        self.session.put(keys.map_updates(stream), data, congestion_control=zenoh.CongestionControl.BLOCK)
        return len(data)
