"""The PostgreSQL store's snapshots (table `snapshots` beside the frames'): the state streamed into its row by binary
COPY from the arrays' own memory, never packed whole; then the deletion of what it covers (services/store/
snapshots.py). A snapshot carries the epoch it was written under and never replaces one of a later epoch."""

from __future__ import annotations

import struct

import numpy as np

from occvo_services.array_pack import chunks, layout
from occvo_services.store.errors import FencedError
from occvo_services.store.snapshots import covered, current, drop_old

_COPY_HEAD = b"PGCOPY\n\xff\r\n\x00" + struct.pack("!ii", 0, 0)


def _field(data: bytes) -> bytes:
    return struct.pack("!i", len(data)) + data


class PgSnapshots:
    def __init__(self, db, frames, leases):
        self.db, self.frames, self.leases, self.q = db, frames, leases, db.dialect.sql

    def write_snapshot(
        self,
        stream: str,
        seq: int,
        state: dict[str, np.ndarray] | bytes,
        created: float | None = None,
        *,
        epoch: int | None = None,
    ) -> bool:
        """The state after frame `seq` replaces the stream's snapshot, then the journal and restored cold rows it
        covers go (as in SQLite, services/store/sqlite_snapshots.py). Two transactions, so that the long first one
        holds no row a frame commit needs: it writes the snapshot unless one of a later epoch is there; the second,
        fenced, deletes what the snapshot covers if the trajectory is still the one snapshotted (False otherwise)."""
        fence = self.leases.fence(stream, epoch)
        created = self.frames.created(stream) if created is None else created
        if created is None:
            return False
        head, items, size = layout(state) if isinstance(state, dict) else (state, [], len(state))
        epoch_field = struct.pack("!i", -1) if epoch is None else _field(struct.pack("!q", epoch))
        row_head = (
            struct.pack("!h", 5)
            + _field(stream.encode())
            + _field(struct.pack("!d", created))
            + _field(struct.pack("!q", seq))
            + epoch_field
            + struct.pack("!i", size)
        )
        self.db.pool.run(lambda conn: _copy_snapshot(conn, stream, epoch, row_head, head, items))
        # unsynced: lost in a crash, the next snapshot deletes what this one covers
        return self.db.write(covered(self.q, stream, seq, created), synced=False, fence=fence)

    def drop_old_snapshots(self, stream: str, *, epoch: int | None = None) -> int:
        """Deletes the stream's snapshot of a trajectory it no longer has; the rows deleted."""

        def tx(cur):
            row = cur.execute(self.q("SELECT created FROM streams WHERE stream = ?"), (stream,)).fetchone()
            return drop_old(self.q, stream, None if row is None else row[0])(cur)

        return self.db.write(tx, fence=self.leases.fence(stream, epoch))

    def snapshot(self, stream: str) -> tuple[int, bytes] | None:
        """(seq, state) of the stream's current trajectory, or None (services/store/snapshots.py)."""

        def read(conn):
            with conn.transaction():  # one view of both rows
                conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ")
                record = conn.execute("SELECT created, last_seq FROM streams WHERE stream = %s", (stream,)).fetchone()
                snap = conn.execute(
                    "SELECT created, seq, state FROM snapshots WHERE stream = %s", (stream,), binary=True
                ).fetchone()
            return record, snap

        return current(*self.db.pool.run(read))

    def sizes(self, stream: str) -> dict[str, int]:
        return self.frames.sizes(stream, (("snapshots", "state"),))


def _copy_snapshot(conn, stream: str, epoch: int | None, row_head: bytes, head: bytes, items: list) -> None:
    """The first transaction: the snapshot row streamed in, unless the lease or a later snapshot fences it."""
    with conn.transaction():
        # one snapshot writer a stream at a time (the row is deleted and copied in again)
        conn.execute("SELECT pg_advisory_xact_lock(54, hashtext(%s))", (stream,))
        if epoch is not None:  # a lease already lost: no need to write megabytes first
            row = conn.execute("SELECT epoch FROM leases WHERE stream = %s", (stream,)).fetchone()
            if row is None or int(row[0]) != epoch:
                raise FencedError(stream, epoch, None if row is None else int(row[0]))
            held = conn.execute("SELECT epoch FROM snapshots WHERE stream = %s", (stream,)).fetchone()
            if held is not None and held[0] is not None and int(held[0]) > epoch:
                raise FencedError(stream, epoch, int(held[0]))
        conn.execute("DELETE FROM snapshots WHERE stream = %s", (stream,))
        with conn.cursor().copy(
            "COPY snapshots (stream, created, seq, epoch, state) FROM STDIN (FORMAT BINARY)"
        ) as copy:
            copy.write(_COPY_HEAD + row_head)
            for chunk in chunks(head, items) if items else (head,):
                copy.write(chunk)
            copy.write(struct.pack("!h", -1))
