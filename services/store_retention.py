"""What the store records for retention, both backends: each stream's client (who wrote it last), its bytes and the
time of its last frame (columns of `streams`), and the reads the registration worker's quotas and stream TTL make
(services/registration/retention.py).

`bytes` is the stream's stored size: measured (its poses, journal, snapshot with the rest of its last page, cold
tiles and, where the map service shares the store, its map tiles) after each snapshot, plus what each frame's commit
and eviction wrote since. A store written before these columns gets them when it is opened; its streams belong to no
client until they are written again, and their TTL runs from their `created`."""

from __future__ import annotations

import sqlite3

RETENTION_COLUMNS = (("client", "TEXT"), ("bytes", "INTEGER NOT NULL DEFAULT 0"), ("last_write", "REAL"))
# one statement in commit_frame's transaction: (time, bytes written, new trajectory, client, stream)
COMMIT_USAGE = (
    "UPDATE streams SET last_write = ?, bytes = ? + (CASE WHEN ? THEN 0 ELSE bytes END), "
    "client = COALESCE(?, client) WHERE stream = ?"
)
GROW = "UPDATE streams SET bytes = bytes + ? WHERE stream = ?"


def frame_bytes(digest: bytes, frame_blob: bytes) -> int:
    """What a frame's commit adds: its journal entry and its pose row (4x4 float64, stamp, digest)."""
    return len(frame_blob) + len(digest) + 136


class RetentionReads:
    """The retention reads and the measurement, on a store with `_read(sql, args)` and `_set_bytes(stream, n)`;
    PARAM is its placeholder."""

    PARAM = "?"

    def _sql(self, sql: str) -> str:
        return sql if self.PARAM == "?" else sql.replace("?", self.PARAM)

    def usage(self, client: str) -> tuple[int, int]:
        """(streams, bytes) the store holds of a client."""
        return self.usage_of(client)[:2]

    def usage_of(self, client: str) -> tuple[int, int, int]:
        """(streams, bytes, its largest stream's bytes) the store holds of a client."""
        sql = "SELECT COUNT(*), COALESCE(SUM(bytes), 0), COALESCE(MAX(bytes), 0) FROM streams WHERE client = ?"
        n, b, biggest = self._read(self._sql(sql), (client,))[0]
        return int(n), int(b), int(biggest)

    def stream_usage(self, stream: str) -> tuple[str | None, int, float] | None:
        """(client, bytes, last write or creation time) of a stored stream; None if it is not stored."""
        rows = self._read(
            self._sql("SELECT client, bytes, COALESCE(last_write, created) FROM streams WHERE stream = ?"), (stream,)
        )
        return None if not rows else (rows[0][0], int(rows[0][1]), float(rows[0][2]))

    def idle_streams(self, before: float, client: str | None = None) -> list[str]:
        """Streams without a frame since `before` (time.time()), the longest idle first; of one client if given."""
        sql = "SELECT stream FROM streams WHERE COALESCE(last_write, created) < ?"
        args: tuple = (before,)
        if client is not None:
            sql, args = sql + " AND client = ?", (before, client)
        return [r[0] for r in self._read(self._sql(sql + " ORDER BY COALESCE(last_write, created)"), args)]

    def measure(self, stream: str) -> int:
        """The stream's stored bytes counted again (after a snapshot, which replaces the journal it covers)."""
        n = sum(v for k, v in self.sizes(stream).items() if k.endswith("_bytes")) + self._slack(stream)
        if self.has_map_tiles():
            n += int(
                self._read(
                    self._sql("SELECT COALESCE(SUM(LENGTH(data)), 0) FROM map_tiles WHERE stream = ?"), (stream,)
                )[0][0]
            )
        self._set_bytes(stream, n)
        self.measure_overhead()
        return n


class SqliteRetention(RetentionReads):
    """The SQLite side: the columns added to an older file, the index, the writes."""

    _overhead = 1.0  # measured when the store opens (TrajectoryStore) and after each measure

    def _add_retention_columns(self) -> None:
        with self._write_lock():
            have = {r[1] for r in self.db.execute("PRAGMA table_info(streams)")}
            for name, kind in RETENTION_COLUMNS:
                if name not in have:
                    try:
                        self.db.execute(f"ALTER TABLE streams ADD COLUMN {name} {kind}")
                    except sqlite3.OperationalError as exc:  # another process added it meanwhile
                        if "duplicate column" not in str(exc):
                            raise
            self.db.execute("CREATE INDEX IF NOT EXISTS streams_client ON streams (client)")

    def has_map_tiles(self) -> bool:
        return bool(self._read("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'map_tiles'"))

    def overhead(self) -> float:
        """The files' pages in use over the bytes the streams record (at least 1): SQLite's pages, B-trees and
        indexes, charged to every stream in proportion. As of the store's opening or last measure: a frame's path
        reads it, and the snapshot file's lock can be held by a snapshot waiting out another writer."""
        return self._overhead

    def measure_overhead(self) -> None:
        """Free pages are left out: the next writes reuse them."""
        used = 0
        for db, lock in ((self.read_db, self.read_lock), (self.snap_db, self.snap_lock)):
            with lock:
                page, count, free = (
                    db.execute(f"PRAGMA {p}").fetchone()[0] for p in ("page_size", "page_count", "freelist_count")
                )
            used += (count - free) * page
        (total,) = self._read("SELECT COALESCE(SUM(bytes), 0) FROM streams")[0]
        self._overhead = max(1.0, used / total) if total else 1.0

    def _slack(self, stream: str) -> int:
        """The snapshot's last page's unused part: a snapshot takes whole pages of its file (64 kB ones)."""
        with self.snap_lock:
            (page,) = self.snap_db.execute("PRAGMA page_size").fetchone()
            row = self.snap_db.execute("SELECT LENGTH(state) FROM snapshots WHERE stream = ?", (stream,)).fetchone()
        return 0 if row is None else -int(row[0]) % page

    def _set_bytes(self, stream: str, n: int) -> None:
        self._write_unsynced(lambda db: db.execute("UPDATE streams SET bytes = ? WHERE stream = ?", (n, stream)))


class PgRetention(RetentionReads):
    """The PostgreSQL side: its schema adds the columns (ADD COLUMN IF NOT EXISTS), the writes."""

    PARAM = "%s"

    def has_map_tiles(self) -> bool:
        return self._read("SELECT to_regclass('map_tiles') IS NOT NULL")[0][0]

    def overhead(self) -> float:
        return 1.0  # the rows' bytes: the server's own files are the operator's

    def measure_overhead(self) -> None:
        """Nothing to measure: the overhead is the rows' bytes (overhead() is 1)."""

    def _slack(self, stream: str) -> int:
        return 0  # TOAST stores a blob in ~2 kB chunks: no page of its own to round up to

    def _set_bytes(self, stream: str, n: int) -> None:
        self.pool.run(lambda conn: conn.execute("UPDATE streams SET bytes = %s WHERE stream = %s", (n, stream)))


# only when a column is missing: an ALTER or CREATE INDEX on `streams` locks it, and opening a store beside running
# writers then deadlocked with them (the schema's earlier statements hold the journal's lock)
PG_RETENTION_SCHEMA = """
DO $$ BEGIN
    IF NOT EXISTS (SELECT 1 FROM information_schema.columns WHERE table_schema = current_schema()
                   AND table_name = 'streams' AND column_name = 'last_write') THEN
        ALTER TABLE streams ADD COLUMN IF NOT EXISTS client TEXT,
            ADD COLUMN IF NOT EXISTS bytes BIGINT NOT NULL DEFAULT 0, ADD COLUMN IF NOT EXISTS last_write DOUBLE PRECISION;
        CREATE INDEX IF NOT EXISTS streams_client ON streams (client);
    END IF;
END $$;
"""
