"""Where the map service keeps its tiles: in memory (MemoryMapStore), in an embedded SQLite file (MapStore) that
survives a restart, or in a PostgreSQL database (services/store/map_tiles_pg.py) shared by replicas on many hosts.

Both hold, per stream, the encoded MapTile bytes of every (ix, iy) with its voxel count and x/y/z bounds, the stream's
tile_m and the seq of the last update. A tile stays until a reset of its stream or an explicit empty tile: the
registration worker may stop sending tiles that left its working set, and those must still be served.

SQLite: WAL journal (readers never block the writer), synchronous=NORMAL (a commit survives a killed process; only
a power cut may lose the last commits), a busy timeout and one short transaction per MapUpdate, so another process
(the registration worker's own tables, services/store/sqlite.py) may write the same file.
"""

from __future__ import annotations

import sqlite3
import threading
from pathlib import Path

import numpy as np

from occvo_schemas.models import MapInfo, MapTileQuery, MapUpdate
from occvo_services.store import map_tiles_sql as sql
from occvo_services.store.dialect import SQLITE
from occvo_services.store.sqlite_wal import enable_wal, transaction

Bounds = MapTileQuery | None

SCHEMA = """
CREATE TABLE IF NOT EXISTS map_streams (
    stream   TEXT PRIMARY KEY,
    tile_m   REAL NOT NULL,
    last_seq INTEGER
);
CREATE TABLE IF NOT EXISTS map_tiles (
    stream TEXT NOT NULL,
    ix     INTEGER NOT NULL,
    iy     INTEGER NOT NULL,
    voxels INTEGER NOT NULL,
    xmin REAL NOT NULL, ymin REAL NOT NULL, zmin REAL NOT NULL,
    xmax REAL NOT NULL, ymax REAL NOT NULL, zmax REAL NOT NULL,
    data   BLOB NOT NULL,  -- last, so info queries never read the blob's overflow pages
    PRIMARY KEY (stream, ix, iy)
);
"""


def _in_bounds(ix: int, iy: int, b: Bounds) -> bool:
    return b is None or (
        (b.ix_min is None or ix >= b.ix_min)
        and (b.ix_max is None or ix <= b.ix_max)
        and (b.iy_min is None or iy >= b.iy_min)
        and (b.iy_max is None or iy <= b.iy_max)
    )


def _tile_rows(update: MapUpdate, encoded: list[bytes]):
    """(ix, iy, voxels, xmin..zmax, data) per tile of an update; voxels 0 means delete."""
    for tile, data in zip(update.tiles, encoded, strict=True):
        n = tile.points.shape[0]
        if n == 0:
            yield tile.ix, tile.iy, 0, None, None, data
        else:
            lo, hi = tile.extent()
            yield tile.ix, tile.iy, n, lo, hi, data


def _info(
    stream: str, tile_m: float, last_seq: int | None, tiles: list[tuple[int, int]], voxels: int, lo, hi
) -> MapInfo:
    return MapInfo(
        stream=stream,
        tile_m=tile_m,
        tile_count=len(tiles),
        voxel_count=voxels,
        last_seq=last_seq,
        bounds_min=tuple(lo) if lo is not None else None,
        bounds_max=tuple(hi) if hi is not None else None,
        tiles=sorted(tiles),
    )


class MemoryMapStore:
    """Tiles in a dict: gone when the process ends."""

    def __init__(self):
        self.lock = threading.Lock()
        self.maps: dict[str, dict] = {}  # stream -> {"tile_m", "last_seq", "tiles": {(ix, iy): (data, n, lo, hi)}}

    def apply(self, update: MapUpdate, encoded: list[bytes]) -> None:
        rows = list(_tile_rows(update, encoded))
        with self.lock:
            m = self.maps.get(update.stream)
            if m is None or update.reset:
                m = self.maps[update.stream] = {"tiles": {}}
            m["tile_m"], m["last_seq"] = update.tile_m, update.seq
            for ix, iy, n, lo, hi, data in rows:
                if n == 0:
                    m["tiles"].pop((ix, iy), None)
                else:
                    m["tiles"][(ix, iy)] = (data, n, lo, hi)

    def streams(self) -> list[str]:
        with self.lock:
            return sorted(self.maps)

    def delete_stream(self, stream: str) -> int:
        with self.lock:
            return len(self.maps.pop(stream, {"tiles": {}})["tiles"])

    def tiles(
        self, stream: str, ix: int | None = None, iy: int | None = None, bounds: Bounds = None, limit: int | None = None
    ) -> list[tuple[int, int, bytes]]:
        """Encoded tiles of a stream: the one at (ix, iy) when both are given, else the first `limit` within bounds."""
        with self.lock:
            m = self.maps.get(stream)
            if m is None:
                return []
            if ix is not None and iy is not None:
                t = m["tiles"].get((ix, iy))
                return [(ix, iy, t[0])] if t and _in_bounds(ix, iy, bounds) else []
            return [(x, y, t[0]) for (x, y), t in sorted(m["tiles"].items()) if _in_bounds(x, y, bounds)][:limit]

    def info(self, stream: str) -> MapInfo | None:
        with self.lock:
            m = self.maps.get(stream)
            if m is None:
                return None
            tiles = dict(m["tiles"])
            tile_m, last = m["tile_m"], m["last_seq"]
        lo = hi = None
        if tiles:
            lo = np.min([t[2] for t in tiles.values()], axis=0).tolist()
            hi = np.max([t[3] for t in tiles.values()], axis=0).tolist()
        return _info(stream, tile_m, last, list(tiles), sum(t[1] for t in tiles.values()), lo, hi)

    def close(self) -> None:
        """Nothing to release: the tiles live in this object (same interface as MapStore.close)."""


class MapStore:
    """Tiles in a SQLite file (tables map_streams, map_tiles); safe to open from several processes at once."""

    def __init__(self, path: str | Path, busy_timeout_s: float = 30.0):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._busy_ms = int(busy_timeout_s * 1000)
        # one connection writes, one reads: in WAL mode a tile query never waits for an update being written
        self._w, self._r = self._connect(), self._connect()
        self._wlock, self._rlock = threading.Lock(), threading.Lock()
        with self._wlock:
            self._w.execute("BEGIN IMMEDIATE")
            try:
                for stmt in SCHEMA.split(";"):
                    if stmt.strip():
                        self._w.execute(stmt)
                self._w.execute("COMMIT")
            except BaseException:
                self._w.execute("ROLLBACK")
                raise

    def _connect(self) -> sqlite3.Connection:
        # isolation_level=None: no implicit transactions; every transaction below is explicit and short
        c = sqlite3.connect(self.path, timeout=self._busy_ms / 1000, isolation_level=None, check_same_thread=False)
        c.execute(f"PRAGMA busy_timeout = {self._busy_ms}")
        enable_wal(c, self._busy_ms / 1000)
        c.execute("PRAGMA synchronous = NORMAL")
        c.execute("PRAGMA journal_size_limit = 67108864")  # truncate the WAL back to 64 MB after checkpoints
        return c

    def apply(self, update: MapUpdate, encoded: list[bytes]) -> None:
        """One transaction: a reset deletes the stream's tiles first; an empty tile deletes that tile."""
        tx = sql.apply(SQLITE.sql, sql.SQLITE_BOUNDS, update, list(_tile_rows(update, encoded)))  # numpy work first
        with self._wlock:
            transaction(self._w, tx)  # BEGIN IMMEDIATE: no read-to-write upgrade that could fail busy

    def delete_stream(self, stream: str) -> int:
        """The stream's map gone (`occvo store delete`); the tiles deleted."""
        with self._wlock:
            return transaction(self._w, sql.delete_stream(SQLITE.sql, stream))

    def streams(self) -> list[str]:
        with self._rlock:
            return [r[0] for r in self._r.execute("SELECT stream FROM map_streams ORDER BY stream")]

    def tiles(
        self, stream: str, ix: int | None = None, iy: int | None = None, bounds: Bounds = None, limit: int | None = None
    ) -> list[tuple[int, int, bytes]]:
        """Encoded tiles of a stream: the one at (ix, iy) when both are given, else the first `limit` within bounds."""
        query, args = sql.tiles(stream, ix, iy, bounds, limit)
        with self._rlock:
            return [(x, y, bytes(d)) for x, y, d in self._r.execute(SQLITE.sql(query), args)]

    def info(self, stream: str) -> MapInfo | None:
        with self._rlock:
            self._r.execute("BEGIN")  # one snapshot for the three reads
            try:
                got = sql.info(SQLITE.sql, sql.SQLITE_BOUNDS, stream)(self._r)
            finally:
                self._r.execute("COMMIT")
        if got is None:
            return None
        row, agg, tiles = got
        lo, hi = (agg[1:4], agg[4:7]) if tiles else (None, None)
        return _info(stream, row[0], row[1], [tuple(t) for t in tiles], int(agg[0]), lo, hi)

    def close(self) -> None:
        with self._wlock, self._rlock:
            self._r.close()
            self._w.close()
