"""Map service: holds the tiles the registration worker publishes (occvo/<stream>/map/updates) and answers
tile queries: occvo/<stream>/map/tile/<ix>/<iy> (one tile), a wildcard such as occvo/<stream>/map/tile/*/*
(a region, optionally bounded by a MapTileQuery payload), and occvo/<stream>/map/info (bounds, tile count, size).

With `store_url` (config or --store-url; store_path and --store-path are its earlier names) the tiles live in a
SQLite file (services/store/map_tiles.py) or a PostgreSQL database (services/store/map_tiles_pg.py): each update is one
transaction, queries read the store, and a restarted service serves what it holds. Without it, in memory."""

from __future__ import annotations

import sys
import time

import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.models import ErrorEvent, MapTileQuery, MapUpdate
from occvo_services.runtime import Worker, WorkerConfig, log_event
from occvo_services.store.errors import StoreUnavailable
from occvo_services.store.factory import open_map_store
from occvo_services.store.url import redact
from occvo_services.wire import encoding
from occvo_services.worker_cli import worker_main


class MapService(Worker):
    """Serves the semantic map as tiles."""

    role = "map"

    def __init__(self, config: WorkerConfig):
        super().__init__(config)
        self.store = open_map_store(config.store_url)

    def declare(self) -> None:
        s = self.session
        self._declared += [
            s.declare_subscriber(keys.map_updates("*"), self._on_update),
            # complete: every map service answers every tile and info query, so a query goes to one of them (the
            # nearest: Zenoh's default target), not to each replica, nor to a queryable that is not complete
            s.declare_queryable(keys.map_tile("*", "*", "*"), self.bounded(self._on_tile_query), complete=True),
            s.declare_queryable(keys.map_info("*"), self.bounded(self._on_info), complete=True),
        ]
        if self.config.store_url:
            log_event(self.log, "map store", path=redact(self.config.store_url), streams=self.store.streams())

    def after_leaving(self) -> None:
        self.store.close()

    def _on_update(self, sample: zenoh.Sample) -> None:
        t0 = time.perf_counter()
        msg = self.decode_input(sample, MapUpdate)
        if msg is None:
            return
        encoded = [encode(t, 1 << 30) for t in msg.tiles]  # encode once, serve many times
        try:
            self.store.apply(msg, encoded)
        except Exception as exc:  # noqa: BLE001 - e.g. the disk is full: report it, keep serving what is stored
            # the store away: the stream's registration worker sends every tile again when it resumes the stream
            self.report_error(
                msg.stream,
                "store_unavailable" if isinstance(exc, StoreUnavailable) else "internal",
                f"map update seq {msg.seq} not stored: {type(exc).__name__}: {exc}",
                str(sample.key_expr),
                msg.seq,
            )
            return
        self.stats.inc("frames_out")
        self.stats.observe("apply_update", (time.perf_counter() - t0) * 1000.0)

    def streams(self) -> list[str]:
        return self.store.streams()

    def _matching_streams(self, query_key: zenoh.KeyExpr, key_of) -> list[str]:
        return [s for s in self.store.streams() if query_key.intersects(zenoh.KeyExpr(key_of(s)))]

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
        tile = keys.tile_of(str(qkey))
        replies = []
        # a region or wildcard gets max_query_tiles tiles a page (a tiny get on occvo/** returned every tile); the
        # tiles are in (stream, ix, iy) order and MapTileQuery.page asks for the next ones
        cap = self.config.max_query_tiles
        page = bounds.page if bounds is not None else 0
        end = (page + 1) * cap + 1  # one more than the page tells whether another page follows
        try:
            for s in sorted(self._matching_streams(qkey, lambda s: keys.map_tile(s, "*", "*"))):
                if len(replies) >= end:
                    break
                for ix, iy, data in self.store.tiles(
                    s, *(tile or (None, None)), bounds=bounds, limit=end - len(replies)
                ):
                    tkey = keys.map_tile(s, ix, iy)
                    if qkey.intersects(zenoh.KeyExpr(tkey)):
                        replies.append((tkey, data))
        except Exception as exc:  # noqa: BLE001 - a store read failed: the querier gets a reason, the service lives
            return self.reply_error(query, stream, "internal", f"reading the map store: {type(exc).__name__}: {exc}")
        if not replies:
            what = f"tile {tile[0]},{tile[1]}" if tile else "any tile"
            return self.reply_error(
                query, stream, "tile_not_found", f"no map {what} for {qkey} (streams with maps: {self.streams()})"
            )
        more = len(replies) > (page + 1) * cap
        replies = replies[page * cap : (page + 1) * cap]
        if not replies:
            return self.reply_error(query, stream, "bad_query", f"page {page} of {qkey} is past its last tile")
        for tkey, data in replies:
            query.reply(tkey, data, encoding=encoding("map_tile"))
        if more:  # not an error of anyone's: the querier pages on
            self.stats.inc("query_pages_truncated")
            query.reply_err(
                encode(
                    ErrorEvent(
                        stream=stream if keys.STREAM_RE.match(stream) else "*",
                        worker=self.worker_id,
                        code="truncated",
                        key=str(qkey)[:200],
                        stamp=time.time(),
                        message=f"{cap} tiles sent (page {page}); ask page {page + 1} for more",
                    )
                ),
                encoding=encoding("error_event"),
            )
        self.stats.observe("tile_query", (time.perf_counter() - t0) * 1000.0)

    def _on_info(self, query: zenoh.Query) -> None:
        found = self._matching_streams(query.key_expr, keys.map_info)
        if not found:
            return self.reply_error(
                query, keys.stream_of(str(query.key_expr)), "tile_not_found", f"no map for {query.key_expr}"
            )
        for s in found:
            info = self.store.info(s)
            if info is not None:
                query.reply(keys.map_info(s), encode(info), encoding=encoding("map_info"))


def _args(p) -> None:
    p.add_argument("--store-path", help="the tiles' store across restarts, as --store-url (default: in memory)")


if __name__ == "__main__":
    sys.exit(worker_main(MapService, extra_args=_args))
