"""How much room a database gives the rows the streams record (retention charges it, services/store/usage.py).
SQLite: the files' pages in use over the rows' bytes, charged to every stream in proportion, and a snapshot's last
64 kB page. PostgreSQL: the rows' bytes (the server's own files are the operator's; TOAST stores a blob in ~2 kB
chunks, no page of its own to round up to)."""

from __future__ import annotations


class SqlitePages:
    def __init__(self, files):
        self.files = files
        self.overhead = 1.0  # as of the store's opening or last measure: a frame's path reads it

    def has_map_tiles(self) -> bool:
        return bool(self.files.read("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'map_tiles'"))

    def measure_overhead(self) -> None:
        """The files' pages in use over the streams' bytes. Not on a frame's path: the snapshot file's lock can be held
        by a snapshot waiting out another writer."""
        (total,) = self.files.read("SELECT COALESCE(SUM(bytes), 0) FROM streams")[0]
        self.overhead = max(1.0, self.files.pages_in_use() / total) if total else 1.0

    def slack(self, stream: str) -> int:
        """The snapshot's last page's unused part: a snapshot takes whole pages of its file (64 kB ones)."""
        (page,) = self.files.read_snapshots("PRAGMA page_size")[0]
        rows = self.files.read_snapshots("SELECT LENGTH(state) FROM snapshots WHERE stream = ?", (stream,))
        return 0 if not rows else -int(rows[0][0]) % page


class PgRows:
    overhead = 1.0

    def __init__(self, db):
        self.db = db

    def has_map_tiles(self) -> bool:
        return self.db.read("SELECT to_regclass('map_tiles') IS NOT NULL")[0][0]

    def measure_overhead(self) -> None:
        """Nothing to measure: the overhead is the rows' bytes."""

    def slack(self, stream: str) -> int:
        return 0
