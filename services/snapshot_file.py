"""The snapshot file beside a trajectory store (<name>.snapshots.sqlite): the latest OccVO state of each stream, and
the deletion of the journal and restored cold rows a durable snapshot covers (services/store.py)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np

from occvo_services.array_pack import chunks, layout, pack_arrays
from occvo_services.sqlite_leases import fence
from occvo_services.sqlite_wal import transaction
from occvo_services.store_api import FencedError

SNAPSHOT_SCHEMA = """
CREATE TABLE IF NOT EXISTS snapshots (
    stream  TEXT PRIMARY KEY,
    created REAL NOT NULL,
    seq     INTEGER NOT NULL,
    state   BLOB NOT NULL,
    epoch   INTEGER  -- the lease epoch it was written under (NULL: unfenced); a later epoch's is never replaced
);
"""


def snapshot_path(path: str | Path) -> str:
    """The snapshot file beside a store file: var/occvo.sqlite -> var/occvo.snapshots.sqlite."""
    path = str(path)
    if path == ":memory:":
        return path
    p = Path(path)
    return str(p.with_name(f"{p.stem}.snapshots{p.suffix or '.sqlite'}"))


class SnapshotFile:
    """TrajectoryStore's snapshots: a second SQLite file, so that a big snapshot never holds the frames' commits."""

    def _move_old_snapshots(self) -> None:
        """A store written before snapshots had their own file: move its snapshots there (its journal needs them).
        In one transaction of the frames' file, so two workers opening the store at once move them once."""

        def old_table(db) -> bool:
            return (
                db.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='snapshots'").fetchone() is not None
            )

        def tx(db):
            if not old_table(db):  # the other worker moved them
                return
            rows = db.execute(
                "SELECT s.stream, t.created, s.seq, s.state FROM snapshots s JOIN streams t USING (stream)"
            ).fetchall()
            transaction(
                self.snap_db,
                lambda snap: snap.executemany(
                    "INSERT OR REPLACE INTO snapshots (stream, created, seq, state) VALUES (?, ?, ?, ?)", rows
                ),
            )
            db.execute("DROP TABLE snapshots")

        if old_table(self.db):  # an open takes no write lock otherwise
            transaction(self.db, tx)

    def _add_snapshot_epochs(self) -> None:
        """A snapshots' file from before leases: its table gets the epoch column (NULL: written unfenced)."""
        with self.snap_lock:
            columns = [r[1] for r in self.snap_db.execute("PRAGMA table_info(snapshots)")]
            if "epoch" not in columns:
                try:
                    self.snap_db.execute("ALTER TABLE snapshots ADD COLUMN epoch INTEGER")
                except sqlite3.OperationalError as exc:  # another process added it meanwhile
                    if "duplicate column" not in str(exc):
                        raise

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
        created = self.created(stream) if created is None else created
        if created is None:
            return False
        if epoch is not None:  # a lease already lost: no need to write megabytes first
            rows = self._read("SELECT epoch FROM leases WHERE stream=?", (stream,))
            if not rows or rows[0][0] != epoch:
                raise FencedError(stream, epoch, rows[0][0] if rows else None)
        in_place = hasattr(sqlite3.Connection, "blobopen")
        if isinstance(state, dict) and not in_place:
            state = pack_arrays(state)
        with self.snap_lock:
            transaction(self.snap_db, lambda db: _write_row(db, stream, created, seq, epoch, state, in_place))
        return self._write_unsynced(lambda db: _covered(db, stream, seq, created, epoch))  # a power cut: next one's

    def drop_old_snapshots(self, stream: str, *, epoch: int | None = None) -> int:
        """Delete the stream's snapshot of a trajectory it no longer has (a reset started another): never read again,
        5 MB or more each. Returns the rows deleted."""
        if epoch is not None:
            self._write(lambda db: fence(db, stream, epoch))
        created = self.created(stream)
        with self.snap_lock:
            return transaction(
                self.snap_db,
                lambda db: (
                    db.execute("DELETE FROM snapshots WHERE stream=? AND created IS NOT ?", (stream, created)).rowcount
                ),
            )

    def snapshot(self, stream: str) -> tuple[int, bytes] | None:
        """(seq, state) of the stream's current trajectory, or None. A snapshot of an older trajectory (a crash
        between its write and the new trajectory's first commit) or of an uncommitted frame does not count."""
        record = self.record(stream)
        with self.snap_lock:
            rows = self.snap_db.execute(
                "SELECT created, seq, state FROM snapshots WHERE stream=?", (stream,)
            ).fetchall()
        if (
            not rows
            or record is None
            or rows[0][0] != record.created
            or record.last_seq is None
            or rows[0][1] > record.last_seq
        ):
            return None
        return int(rows[0][1]), rows[0][2]


def _write_row(db, stream: str, created: float, seq: int, epoch: int | None, state, in_place: bool) -> None:
    """The snapshot's row, unless one of a later epoch is there; arrays written into the row in place."""
    if epoch is not None:
        held = db.execute("SELECT epoch FROM snapshots WHERE stream=?", (stream,)).fetchone()
        if held is not None and held[0] is not None and held[0] > epoch:
            raise FencedError(stream, epoch, held[0])
    if not in_place:
        db.execute(
            "INSERT OR REPLACE INTO snapshots (stream, created, seq, state, epoch) VALUES (?, ?, ?, ?, ?)",
            (stream, created, seq, state, epoch),
        )
        return
    head, items, size = layout(state) if isinstance(state, dict) else (state, [], len(state))
    rowid = db.execute(
        "INSERT OR REPLACE INTO snapshots (stream, created, seq, state, epoch) VALUES (?, ?, ?, zeroblob(?), ?)",
        (stream, created, seq, size, epoch),
    ).lastrowid
    with db.blobopen("snapshots", "state", rowid) as blob:
        for chunk in chunks(head, items):
            blob.write(chunk)


def _covered(db, stream: str, seq: int, created: float, epoch: int | None) -> bool:
    """In the frames' file, fenced: the journal and restored cold rows the snapshot covers go, if the trajectory is
    still the one snapshotted."""
    fence(db, stream, epoch)
    if db.execute("SELECT created FROM streams WHERE stream=?", (stream,)).fetchone() != (created,):
        return False
    db.execute("DELETE FROM journal WHERE stream=? AND seq<=?", (stream, seq))
    db.execute("DELETE FROM cold_tiles WHERE stream=? AND restored_seq IS NOT NULL AND restored_seq<=?", (stream, seq))
    db.execute("UPDATE streams SET snapshot_seq=? WHERE stream=?", (seq, stream))
    return True
