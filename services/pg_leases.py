"""Streams' leases in the PostgreSQL store (services/store_pg.py; the semantics in services/store_api.py). Expiry
by the server's clock (now()), so the hosts' clocks do not matter."""

from __future__ import annotations

from occvo_services.store_api import FencedError, Lease


def fence(conn, stream: str, epoch: int | None, required: bool = False) -> None:
    """Inside a write's transaction: FencedError unless the stream's lease is still at `epoch` (None: unfenced, unless
    `required`); the lease row stays locked against a takeover until the write commits."""
    if epoch is None:
        if required:
            raise FencedError(stream, None, None)
        return
    row = conn.execute("SELECT epoch, owner FROM leases WHERE stream = %s FOR SHARE", (stream,)).fetchone()
    if row is None or int(row[0]) != epoch:
        raise FencedError(stream, epoch, None if row is None else int(row[0]), None if row is None else row[1])


class PgLeases:
    """PgTrajectoryStore's lease methods (self.pool runs a call on a connection, self._read a query)."""

    fenced_only = False  # placement "members" sets it: every write fenced, one without an epoch refused

    def _fence(self, conn, stream: str, epoch: int | None) -> None:
        """What a fenced write calls in its transaction."""
        fence(conn, stream, epoch, self.fenced_only)

    def acquire(self, stream: str, owner: str, ttl_s: float, take_from: str | None = None) -> int | None:
        """The stream's lease for `owner` for ttl_s: its epoch, or None while another owner holds it. Taking it
        from another owner (expired, released, or `take_from`: one known lost) moves the epoch on; the same owner
        keeps its epoch."""
        rows = self.pool.run(
            lambda conn: conn.execute(
                "INSERT INTO leases AS l VALUES (%s, %s, 1, now() + make_interval(secs => %s)) "
                "ON CONFLICT (stream) DO UPDATE SET epoch = l.epoch + (l.owner IS DISTINCT FROM excluded.owner)::int, "
                "owner = excluded.owner, expires_at = excluded.expires_at "
                "WHERE l.owner = excluded.owner OR l.expires_at <= now() OR l.owner = %s RETURNING epoch",
                (stream, owner, float(ttl_s), take_from),
            ).fetchall()
        )
        return int(rows[0][0]) if rows else None

    def renew(self, owner: str, ttl_s: float) -> list[str]:
        """Extends every unexpired lease of `owner` by ttl_s from now; the streams it still holds."""
        rows = self.pool.run(
            lambda conn: conn.execute(
                "UPDATE leases SET expires_at = now() + make_interval(secs => %s) "
                "WHERE owner = %s AND expires_at > now() RETURNING stream",
                (float(ttl_s), owner),
            ).fetchall()
        )
        return sorted(r[0] for r in rows)

    def drop_unused_leases(self, owner: str, keep: list[str]) -> int:
        """The lease rows of streams that never stored a frame deleted: `owner`'s but those in `keep`, and expired or
        released ones of any owner (a worker gone for good leaves its rows); how many."""
        return self.pool.run(
            lambda conn: (
                conn.execute(
                    "DELETE FROM leases l WHERE ((l.owner = %s AND NOT (l.stream = ANY(%s))) OR l.expires_at <= now()) "
                    "AND NOT EXISTS (SELECT 1 FROM streams s WHERE s.stream = l.stream)",
                    (owner, list(keep)),
                ).rowcount
            )
        )

    def release(self, stream: str, owner: str) -> bool:
        """Gives the stream's lease up (the next owner moves the epoch on); False if `owner` did not hold it."""
        return self.pool.run(
            lambda conn: (
                conn.execute(
                    "UPDATE leases SET owner = NULL, expires_at = now() WHERE stream = %s AND owner = %s",
                    (stream, owner),
                ).rowcount
                > 0
            )
        )

    def owner_of(self, stream: str) -> str | None:
        """The owner holding the stream's lease now (None: free, released or expired)."""
        rows = self._read("SELECT owner FROM leases WHERE stream = %s AND expires_at > now()", (stream,))
        return rows[0][0] if rows else None

    def leases(self) -> list[Lease]:
        rows = self._read(
            "SELECT stream, owner, epoch, EXTRACT(EPOCH FROM expires_at - now()) FROM leases ORDER BY stream"
        )
        return [Lease(s, o, int(e), float(r)) for s, o, e, r in rows]
