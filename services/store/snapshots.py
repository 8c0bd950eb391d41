"""What a snapshot means, in either database: the OccVO state after frame `seq` of the stream's trajectory
`created`. It counts only if that is the stream's current trajectory and the frame is committed there; the journal
and restored cold rows it covers are deleted only after it is durable (a second transaction), so a crash between
the two leaves a valid (older) resume point. Each database writes the row its own way (services/store/
sqlite_snapshots.py, pg_snapshots.py)."""

from __future__ import annotations

from occvo_services.store.records import StreamRecord


def covered(q, stream: str, seq: int, created: float):
    """The fenced transaction after a snapshot is durable: fn(cur) deleting the journal and restored cold rows it
    covers if the trajectory is still the one snapshotted; False otherwise. `q` renders for the database."""

    def tx(cur) -> bool:
        row = cur.execute(q("SELECT created FROM streams WHERE stream = ?{for_update}"), (stream,)).fetchone()
        if row is None or row[0] != created:
            return False
        cur.execute(q("DELETE FROM journal WHERE stream = ? AND seq <= ?"), (stream, seq))
        cur.execute(
            q("DELETE FROM cold_tiles WHERE stream = ? AND restored_seq IS NOT NULL AND restored_seq <= ?"),
            (stream, seq),
        )
        cur.execute(q("UPDATE streams SET snapshot_seq = ? WHERE stream = ?"), (seq, stream))
        return True

    return tx


def current(record: StreamRecord | tuple | None, snap) -> tuple[int, bytes] | None:
    """(seq, state) of a (created, seq, state) snapshot row if it counts for the stream's (created, last_seq), else
    None: a snapshot of an older trajectory (a crash between its write and the new trajectory's first commit) or of
    an uncommitted frame does not."""
    if record is not None and isinstance(record, StreamRecord):
        record = (record.created, record.last_seq)
    if snap is None or record is None or snap[0] != record[0] or record[1] is None or snap[1] > record[1]:
        return None
    return int(snap[1]), snap[2]


def drop_old(q, stream: str, created: float | None):
    """fn(cur) deleting the stream's snapshot of a trajectory it no longer has (a reset started another): never read
    again, 5 MB or more each; the rows deleted."""
    return lambda cur: (
        cur.execute(q("DELETE FROM snapshots WHERE stream = ? AND created {distinct} ?"), (stream, created)).rowcount
    )
