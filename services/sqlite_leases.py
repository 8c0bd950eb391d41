"""Streams' leases in the SQLite store (services/store.py; the semantics in services/store_api.py): a `leases` table
in the frames' file, so that a fenced write checks the lease in its own write transaction (SQLite's one writer a file
makes the check and the write atomic against a takeover). Expiry by this host's clock: a SQLite file has one host."""

from __future__ import annotations

import time

from occvo_services.store_api import FencedError, Lease

LEASES_SCHEMA = """
CREATE TABLE IF NOT EXISTS leases (
    stream     TEXT PRIMARY KEY,
    owner      TEXT,
    epoch      INTEGER NOT NULL,
    expires_at REAL NOT NULL
);
"""


def fence(db, stream: str, epoch: int | None, required: bool = False) -> None:
    """Inside a write transaction: FencedError unless the stream's lease is still at `epoch` (None: unfenced, unless
    `required`)."""
    if epoch is None:
        if required:
            raise FencedError(stream, None, None)
        return
    row = db.execute("SELECT epoch, owner FROM leases WHERE stream=?", (stream,)).fetchone()
    if row is None or int(row[0]) != epoch:
        raise FencedError(stream, epoch, None if row is None else int(row[0]), None if row is None else row[1])


class SqliteLeases:
    """TrajectoryStore's lease methods (self._write runs a write transaction, self._read a read)."""

    fenced_only = False  # placement "members" sets it: every write fenced, one without an epoch refused

    def acquire(self, stream: str, owner: str, ttl_s: float, take_from: str | None = None) -> int | None:
        """The stream's lease for `owner` for ttl_s: its epoch, or None while another owner holds it. Taking it
        from another owner (expired, released, or `take_from`: one known lost) moves the epoch on; the same owner
        keeps its epoch."""

        def tx(db):
            now = time.time()
            row = db.execute("SELECT owner, epoch, expires_at FROM leases WHERE stream=?", (stream,)).fetchone()
            if row is None:
                epoch = 1
            elif row[0] == owner or row[2] <= now or (take_from is not None and row[0] == take_from):
                epoch = int(row[1]) + (row[0] != owner)
            else:
                return None
            db.execute("INSERT OR REPLACE INTO leases VALUES (?, ?, ?, ?)", (stream, owner, epoch, now + ttl_s))
            return epoch

        return self._write(tx)

    def renew(self, owner: str, ttl_s: float) -> list[str]:
        """Extends every unexpired lease of `owner` by ttl_s from now; the streams it still holds."""

        def tx(db):
            now = time.time()
            held = [
                r[0]
                for r in db.execute("SELECT stream FROM leases WHERE owner=? AND expires_at>?", (owner, now)).fetchall()
            ]
            db.execute("UPDATE leases SET expires_at=? WHERE owner=? AND expires_at>?", (now + ttl_s, owner, now))
            return sorted(held)

        return self._write(tx)

    def drop_unused_leases(self, owner: str, keep: list[str]) -> int:
        """The lease rows of streams that never stored a frame deleted: `owner`'s but those in `keep`, and expired or
        released ones of any owner (a worker gone for good leaves its rows); how many."""

        def tx(db):
            sql = "SELECT stream, owner, expires_at FROM leases WHERE stream NOT IN (SELECT stream FROM streams)"
            now, rows = time.time(), db.execute(sql).fetchall()
            gone = [(s,) for s, o, x in rows if x <= now or (o == owner and s not in set(keep))]
            db.executemany("DELETE FROM leases WHERE stream=?", gone)
            return len(gone)

        return self._write(tx)

    def release(self, stream: str, owner: str) -> bool:
        """Gives the stream's lease up (the next owner moves the epoch on); False if `owner` did not hold it."""
        return self._write(
            lambda db: (
                db.execute(
                    "UPDATE leases SET owner=NULL, expires_at=? WHERE stream=? AND owner=?",
                    (time.time(), stream, owner),
                ).rowcount
                > 0
            )
        )

    def owner_of(self, stream: str) -> str | None:
        """The owner holding the stream's lease now (None: free, released or expired)."""
        rows = self._read("SELECT owner FROM leases WHERE stream=? AND expires_at>?", (stream, time.time()))
        return rows[0][0] if rows else None

    def leases(self) -> list[Lease]:
        now = time.time()
        rows = self._read("SELECT stream, owner, epoch, expires_at FROM leases ORDER BY stream")
        return [Lease(s, o, int(e), float(x) - now) for s, o, e, x in rows]
