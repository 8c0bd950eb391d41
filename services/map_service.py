"""Map service: holds the tiles the registration worker publishes (occvo/<stream>/map/updates) and answers
tile queries: occvo/<stream>/map/tile/<ix>/<iy> (one tile), a wildcard such as occvo/<stream>/map/tile/*/*
(a region, optionally bounded by a MapTileQuery payload), and occvo/<stream>/map/info (bounds, tile count, size)."""

from __future__ import annotations

import sys
import threading
import time

import numpy as np
import zenoh

from schemas import keys
from schemas.codec import CodecError, decode, encode
from schemas.models import MapInfo, MapTileQuery, MapUpdate
from services.runtime import Worker, WorkerConfig, worker_main


class StreamMap:
    def __init__(self, tile_m: float):
        self.tile_m = tile_m
        self.tiles: dict[tuple[int, int], tuple[bytes, int, np.ndarray]] = {}  # encoded MapTile, voxels, (min, max)
        self.last_seq: int | None = None


class MapService(Worker):
    """Serves the semantic map as tiles."""

    role = "map"

    def __init__(self, config: WorkerConfig):
        super().__init__(config)
        self.maps: dict[str, StreamMap] = {}
        self.lock = threading.Lock()

    def declare(self) -> None:
        s = self.session
        self._declared += [
            s.declare_subscriber(keys.map_updates("*"), self._on_update),
            s.declare_queryable(keys.map_tile("*", "*", "*"), self._on_tile_query),
            s.declare_queryable(keys.map_info("*"), self._on_info),
        ]

    def _on_update(self, sample: zenoh.Sample) -> None:
        t0 = time.perf_counter()
        msg = self.decode_input(sample, MapUpdate)
        if msg is None:
            return
        encoded = [(t, encode(t, 1 << 30)) for t in msg.tiles]  # encode once, serve many times
        with self.lock:
            m = self.maps.get(msg.stream)
            if m is None or msg.reset:
                m = self.maps[msg.stream] = StreamMap(msg.tile_m)
            m.tile_m = msg.tile_m
            for tile, data in encoded:
                n = tile.points.shape[0]
                if n == 0:
                    m.tiles.pop((tile.ix, tile.iy), None)
                else:
                    p = tile.points.to_numpy()
                    m.tiles[(tile.ix, tile.iy)] = (data, n, np.stack([p.min(0), p.max(0)]))
            m.last_seq = msg.seq
        self.stats.inc("frames_out")
        self.stats.observe("apply_update", (time.perf_counter() - t0) * 1000.0)

    def streams(self) -> list[str]:
        with self.lock:
            return sorted(self.maps)

    def _streams_for(self, query_key: zenoh.KeyExpr, key_of) -> list[tuple[str, StreamMap]]:
        with self.lock:
            items = list(self.maps.items())
        return [(s, m) for s, m in items if query_key.intersects(zenoh.KeyExpr(key_of(s)))]

    def _on_tile_query(self, query: zenoh.Query) -> None:
        t0 = time.perf_counter()
        qkey = query.key_expr
        stream = keys.stream_of(str(qkey))
        bounds = None
        if query.payload is not None and len(query.payload.to_bytes()):
            try:
                bounds = decode(query.payload.to_bytes(), MapTileQuery, self.config.max_message_bytes)
            except CodecError as exc:
                return self.reply_error(query, stream, exc.code, f"tile query payload: {exc.message}")
        replies = []
        for s, m in self._streams_for(qkey, lambda s: keys.map_tile(s, "*", "*")):
            with self.lock:
                tiles = list(m.tiles.items())
            for (ix, iy), (data, _, _) in tiles:
                tkey = keys.map_tile(s, ix, iy)
                if not qkey.intersects(zenoh.KeyExpr(tkey)):
                    continue
                if bounds is not None and not (
                        (bounds.ix_min is None or ix >= bounds.ix_min) and (bounds.ix_max is None or ix <= bounds.ix_max)
                        and (bounds.iy_min is None or iy >= bounds.iy_min) and (bounds.iy_max is None or iy <= bounds.iy_max)):
                    continue
                replies.append((tkey, data))
        if not replies:
            tile = keys.tile_of(str(qkey))
            what = f"tile {tile[0]},{tile[1]}" if tile else "any tile"
            return self.reply_error(query, stream, "tile_not_found", f"no map {what} for {qkey} (streams with maps: {sorted(self.maps)})")
        for tkey, data in replies:
            query.reply(tkey, data)
        self.stats.observe("tile_query", (time.perf_counter() - t0) * 1000.0)

    def _on_info(self, query: zenoh.Query) -> None:
        found = self._streams_for(query.key_expr, keys.map_info)
        if not found:
            return self.reply_error(query, keys.stream_of(str(query.key_expr)), "tile_not_found", f"no map for {query.key_expr}")
        for s, m in found:
            with self.lock:
                tiles = dict(m.tiles)
                last = m.last_seq
            lo = hi = None
            if tiles:
                ext = np.stack([b for _, _, b in tiles.values()])
                lo, hi = tuple(ext[:, 0].min(0).tolist()), tuple(ext[:, 1].max(0).tolist())
            info = MapInfo(stream=s, tile_m=m.tile_m, tile_count=len(tiles), voxel_count=sum(n for _, n, _ in tiles.values()),
                           last_seq=last, bounds_min=lo, bounds_max=hi, tiles=sorted(tiles))
            query.reply(keys.map_info(s), encode(info))


if __name__ == "__main__":
    sys.exit(worker_main(MapService))
