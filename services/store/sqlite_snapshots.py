"""The SQLite store's snapshots, in the file beside the frames' (<name>.snapshots.sqlite, services/store/
sqlite_files.py): the latest OccVO state of each stream, written into its row in place, then the deletion of what it
covers in the frames' file (services/store/snapshots.py)."""

from __future__ import annotations

import sqlite3

import numpy as np

from occvo_services.array_pack import chunks, layout, pack_arrays
from occvo_services.store.errors import FencedError
from occvo_services.store.snapshots import covered, current, drop_old

ROW = "INSERT OR REPLACE INTO snapshots (stream, created, seq, state, epoch) VALUES (?, ?, ?, {}, ?)"


class SqliteSnapshots:
    def __init__(self, files, frames, leases):
        self.files, self.frames, self.leases = files, frames, leases

    def write_snapshot(
        self,
        stream: str,
        seq: int,
        state: dict[str, np.ndarray] | bytes,
        created: float | None = None,
        *,
        epoch: int | None = None,
    ) -> bool:
        """The state after frame `seq` (arrays, or pack_arrays' bytes) replaces the older snapshot; then the journal
        up to it and the cold rows restored by then go. Arrays are written into the row in place, each from its own
        memory (Python >= 3.11): packing them first would hold a copy of the whole state, and the worker's peak RSS
        with it. Frame commits go on meanwhile (another file). `created`: the trajectory the state belongs to
        (created(stream) when the state was taken), by default the current one. False, and the journal kept, if the
        stream started another since. Given `epoch`: FencedError if the stream's lease has moved on (checked in the
        frames' file's transaction; the snapshot's file, another file, only refuses to replace a snapshot of a later
        epoch: one written under a lost lease covers frames its writer committed, so it stays a valid resume point)."""
        fence = self.leases.fence(stream, epoch)
        created = self.frames.created(stream) if created is None else created
        if created is None:
            return False
        if epoch is not None:  # a lease already lost: no need to write megabytes first
            rows = self.files.read("SELECT epoch FROM leases WHERE stream = ?", (stream,))
            if not rows or rows[0][0] != epoch:
                raise FencedError(stream, epoch, rows[0][0] if rows else None)
        in_place = hasattr(sqlite3.Connection, "blobopen")
        if isinstance(state, dict) and not in_place:
            state = pack_arrays(state)
        self.files.snapshots(lambda db: _write_row(db, stream, created, seq, epoch, state, in_place))
        # unsynced: lost in a power cut, the next snapshot deletes what this one covers
        return self.files.write(covered(self.files.dialect.sql, stream, seq, created), synced=False, fence=fence)

    def drop_old_snapshots(self, stream: str, *, epoch: int | None = None) -> int:
        """Delete the stream's snapshot of a trajectory it no longer has; the rows deleted."""
        fence = self.leases.fence(stream, epoch)
        if epoch is not None:
            self.files.write(lambda db: None, fence=fence)
        return self.files.snapshots(drop_old(self.files.dialect.sql, stream, self.frames.created(stream)))

    def snapshot(self, stream: str) -> tuple[int, bytes] | None:
        """(seq, state) of the stream's current trajectory, or None (services/store/snapshots.py)."""
        record = self.frames.record(stream)
        rows = self.files.read_snapshots("SELECT created, seq, state FROM snapshots WHERE stream = ?", (stream,))
        return current(record, rows[0] if rows else None)

    def sizes(self, stream: str) -> dict[str, int]:
        sql = "SELECT COUNT(*), COALESCE(SUM(LENGTH(state)), 0) FROM snapshots WHERE stream = ?"
        n, b = self.files.read_snapshots(sql, (stream,))[0]
        return {"snapshots_rows": int(n), "snapshots_bytes": int(b)}

    def delete(self, stream: str) -> None:
        self.files.snapshots(lambda db: db.execute("DELETE FROM snapshots WHERE stream = ?", (stream,)))


def _write_row(db, stream: str, created: float, seq: int, epoch: int | None, state, in_place: bool) -> None:
    """The snapshot's row, unless one of a later epoch is there; arrays written into the row in place."""
    if epoch is not None:
        held = db.execute("SELECT epoch FROM snapshots WHERE stream = ?", (stream,)).fetchone()
        if held is not None and held[0] is not None and held[0] > epoch:
            raise FencedError(stream, epoch, held[0])
    if not in_place:
        db.execute(ROW.format("?"), (stream, created, seq, state, epoch))
        return
    head, items, size = layout(state) if isinstance(state, dict) else (state, [], len(state))
    rowid = db.execute(ROW.format("zeroblob(?)"), (stream, created, seq, size, epoch)).lastrowid
    with db.blobopen("snapshots", "state", rowid) as blob:
        for chunk in chunks(head, items):
            blob.write(chunk)
