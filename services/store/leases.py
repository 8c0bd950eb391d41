"""Streams' leases, in either database: each stream has at most one owning worker at a time, recorded with a fencing
epoch. A write given `epoch` checks it against the stream's lease inside its own transaction (fence) and raises
FencedError, writing nothing, when another owner has taken the stream since (its epoch is higher). epoch=None writes
unfenced (one embedded worker, the `occvo store` command), unless the store is `fenced_only` (placement "members":
FencedError, nothing written). In PostgreSQL the fence locks the lease row (FOR SHARE) until the write commits, so a
takeover waits for those writes and they for it; SQLite's one writer a file does the same. Expiry by the database's
clock (services/store/dialect.py)."""

from __future__ import annotations

from occvo_services.store.errors import FencedError
from occvo_services.store.records import Lease

ACQUIRE = (
    "INSERT INTO leases AS l VALUES (?, ?, 1, {later}) ON CONFLICT (stream) DO UPDATE SET "
    "epoch = l.epoch + (CASE WHEN l.owner {distinct} excluded.owner THEN 1 ELSE 0 END), "
    "owner = excluded.owner, expires_at = excluded.expires_at "
    "WHERE l.owner = excluded.owner OR l.expires_at <= {now} OR l.owner = ?"
)


class LeaseTable:
    """The `leases` table of a store's database (`db`: write(fn, ...) runs a transaction, read(sql, args) a query)."""

    def __init__(self, db, fenced_only: bool = False):
        self.db, self.q = db, db.dialect.sql
        self.fenced_only = fenced_only  # placement "members": every write fenced, one without an epoch refused

    def fence(self, stream: str, epoch: int | None):
        """What a write of the stream runs first in its transaction: FencedError unless the stream's lease is still
        at `epoch` (None: unfenced, unless fenced_only); the lease row stays held against a takeover until the write
        commits."""
        if epoch is None and self.fenced_only:
            raise FencedError(stream, None, None)
        sql = self.q("SELECT epoch, owner FROM leases WHERE stream = ?{for_share}")

        def check(cur) -> None:
            if epoch is None:
                return
            row = cur.execute(sql, (stream,)).fetchone()
            if row is None or int(row[0]) != epoch:
                raise FencedError(stream, epoch, None if row is None else int(row[0]), None if row is None else row[1])

        return check

    def acquire(self, stream: str, owner: str, ttl_s: float, take_from: str | None = None) -> int | None:
        """The stream's lease for `owner` for ttl_s: its epoch, or None while another owner holds it. Taking it
        from another owner (expired, released, or `take_from`: one known lost) moves the epoch on; the same owner
        keeps its epoch."""

        def tx(cur):
            cur.execute(self.q(ACQUIRE), (stream, owner, float(ttl_s), take_from))
            row = cur.execute(self.q("SELECT owner, epoch FROM leases WHERE stream = ?"), (stream,)).fetchone()
            return int(row[1]) if row[0] == owner else None

        return self.db.write(tx)

    def renew(self, owner: str, ttl_s: float) -> list[str]:
        """Extends every unexpired lease of `owner` by ttl_s from now; the streams it still holds."""

        def tx(cur):
            sql = "SELECT stream FROM leases WHERE owner = ? AND expires_at > {now}{for_update}"
            held = [r[0] for r in cur.execute(self.q(sql), (owner,)).fetchall()]
            cur.execute(
                self.q("UPDATE leases SET expires_at = {later} WHERE owner = ? AND expires_at > {now}"),
                (float(ttl_s), owner),
            )
            return sorted(held)

        return self.db.write(tx)

    def drop_unused_leases(self, owner: str, keep: list[str]) -> int:
        """The lease rows of streams that never stored a frame deleted: `owner`'s but those in `keep`, and expired or
        released ones of any owner (a worker gone for good leaves its rows); how many."""
        keep = list(keep)
        mine = f"l.owner = ? AND l.stream NOT IN ({', '.join('?' * len(keep))})" if keep else "l.owner = ?"
        sql = self.q(
            f"DELETE FROM leases AS l WHERE (({mine}) OR l.expires_at <= {{now}}) "
            "AND NOT EXISTS (SELECT 1 FROM streams s WHERE s.stream = l.stream)"
        )
        return self.db.write(lambda cur: cur.execute(sql, (owner, *keep)).rowcount)

    def release(self, stream: str, owner: str) -> bool:
        """Gives the stream's lease up (the next owner moves the epoch on); False if `owner` did not hold it."""
        sql = self.q("UPDATE leases SET owner = NULL, expires_at = {now} WHERE stream = ? AND owner = ?")
        return self.db.write(lambda cur: cur.execute(sql, (stream, owner)).rowcount > 0)

    def owner_of(self, stream: str) -> str | None:
        """The owner holding the stream's lease now (None: free, released or expired)."""
        rows = self.db.read("SELECT owner FROM leases WHERE stream = ? AND expires_at > {now}", (stream,))
        return rows[0][0] if rows else None

    def leases(self) -> list[Lease]:
        rows = self.db.read("SELECT stream, owner, epoch, {remaining} FROM leases ORDER BY stream")
        return [Lease(s, o, int(e), float(r)) for s, o, e, r in rows]
