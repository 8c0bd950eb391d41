"""The frame log, in either database: each stream's record, its published poses and the journal of the frames
registered since its snapshot. A frame is committed atomically before its pose is published (commit_frame); what it
did after that (a relocalised pose, the tiles it evicted and restored) follows without a sync of its own
(finish_frame): a frame stopped before it is finished by the replay of the journal (the registration worker's
resume), and the next frame's synced commit carries it (commits are ordered), one sync a frame, not two."""

from __future__ import annotations

import time
from collections.abc import Iterable

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_services.array_pack import pack_arrays
from occvo_services.store.blobs import unpack_frame
from occvo_services.store.records import StoredPose, StreamRecord, pose_bytes, stored_pose
from occvo_services.store.usage import COMMIT_USAGE, GROW, frame_bytes

PER_STREAM = ("poses", "journal", "cold_tiles")  # what a new trajectory drops
NEW_TRAJECTORY = (
    "INSERT INTO streams (stream, created, last_seq) VALUES (?, ?, ?) ON CONFLICT (stream) DO UPDATE SET "
    "created = excluded.created, last_seq = excluded.last_seq, snapshot_seq = NULL"
)
NEXT_FRAME = (
    "INSERT INTO streams (stream, created, last_seq) VALUES (?, ?, ?) "
    "ON CONFLICT (stream) DO UPDATE SET last_seq = excluded.last_seq"
)
POSE = (
    "INSERT INTO poses VALUES (?, ?, ?, ?, ?, ?) ON CONFLICT (stream, seq) DO UPDATE SET "
    "stamp = excluded.stamp, digest = excluded.digest, status = excluded.status, pose = excluded.pose"
)
JOURNAL = "INSERT INTO journal VALUES (?, ?, ?) ON CONFLICT (stream, seq) DO UPDATE SET frame = excluded.frame"
RELOCALISED = "UPDATE poses SET status = 'relocalised', pose = ? WHERE stream = ? AND seq = ?"
RESTORED = "UPDATE cold_tiles SET restored_seq = ? WHERE stream = ? AND ix = ? AND iy = ? AND evicted_seq = ?"
EVICTED = (
    "INSERT INTO cold_tiles VALUES (?, ?, ?, ?, NULL, ?) ON CONFLICT (stream, ix, iy, evicted_seq) "
    "DO UPDATE SET restored_seq = NULL, block = excluded.block"
)
POSE_COLUMNS = "SELECT seq, stamp, digest, status, pose FROM poses WHERE stream = ?"


class FrameLog:
    """The frame log of a store's database (`db`), its writes fenced by `leases` (services/store/leases.py)."""

    def __init__(self, db, leases):
        self.db, self.leases, self.q = db, leases, db.dialect.sql

    def streams(self) -> list[str]:
        return [r[0] for r in self.db.read("SELECT stream FROM streams ORDER BY stream")]

    def record(self, stream: str) -> StreamRecord | None:
        rows = self.db.read("SELECT stream, created, last_seq, snapshot_seq FROM streams WHERE stream = ?", (stream,))
        return StreamRecord(*rows[0]) if rows else None

    def created(self, stream: str) -> float | None:
        """Identifies the stream's current trajectory (its creation time)."""
        rows = self.db.read("SELECT created FROM streams WHERE stream = ?", (stream,))
        return rows[0][0] if rows else None

    def pose(self, stream: str, seq: int) -> StoredPose | None:
        rows = self.db.read(POSE_COLUMNS + " AND seq = ?", (stream, seq), True)
        return stored_pose(rows[0]) if rows else None

    def poses(self, stream: str) -> list[StoredPose]:
        return [stored_pose(r) for r in self.db.read(POSE_COLUMNS + " ORDER BY seq", (stream,), True)]

    def journal(self, stream: str, after_seq: int | None) -> list[tuple[int, OccupancyFrame]]:
        rows = self.db.read(
            "SELECT seq, frame FROM journal WHERE stream = ? AND seq > ? ORDER BY seq",
            (stream, -1 if after_seq is None else after_seq),
            True,
        )
        return [(int(s), unpack_frame(b)) for s, b in rows]

    def commit_frame(
        self,
        stream: str,
        seq: int,
        stamp: float,
        digest: bytes,
        status: str,
        pose: np.ndarray,
        frame_blob: bytes,
        new_trajectory: bool = False,
        *,
        epoch: int | None = None,
        client: str | None = None,
    ) -> dict[str, float]:
        """One frame, atomically and durably, before its pose is published: the pose and the journal entry.
        new_trajectory first drops everything of the stream. Returns where the time went, in ms: "lock" (this
        store's other writers, or waiting for a connection), "begin" (other processes', or the lease), "commit".
        Given `epoch`, FencedError and nothing written if the stream's lease has moved on. `client`: whose the
        stream is now (retention), its bytes and last write updated in the same transaction."""
        row = (stream, seq, float(stamp), digest, status, pose_bytes(pose))
        grown, q = frame_bytes(digest, frame_blob), self.q

        def tx(cur):
            now = time.time()
            if new_trajectory:
                for table in PER_STREAM:
                    cur.execute(q(f"DELETE FROM {table} WHERE stream = ?"), (stream,))
            cur.execute(q(NEW_TRAJECTORY if new_trajectory else NEXT_FRAME), (stream, now, seq))
            cur.execute(q(POSE), row)
            cur.execute(q(JOURNAL), (stream, seq, frame_blob))
            cur.execute(q(COMMIT_USAGE), (now, grown, new_trajectory, client, stream))

        phases: dict[str, float] = {}
        self.db.write(tx, phases, fence=self.leases.fence(stream, epoch))
        return phases

    def finish_frame(
        self,
        stream: str,
        seq: int,
        pose: np.ndarray | None = None,
        evicted: dict | None = None,
        restored: Iterable[tuple[int, int, int]] = (),
        *,
        epoch: int | None = None,
    ) -> None:
        """What a committed frame did after its pose was published, atomically: its relocalised pose (a loop
        closed; status "relocalised"), the tiles it evicted ({(ix, iy): block arrays}) and the cold rows it restored
        ((ix, iy, evicted_seq)); no sync of its own (see above)."""
        blobs = {k: pack_arrays(b) for k, b in (evicted or {}).items()}  # before the lock
        restored, q = list(restored), self.q

        def tx(cur):
            if pose is not None:
                cur.execute(q(RELOCALISED), (pose_bytes(pose), stream, seq))
            if restored:
                cur.executemany(q(RESTORED), [(seq, stream, ix, iy, e) for ix, iy, e in restored])
            if blobs:
                cur.executemany(q(EVICTED), [(stream, ix, iy, seq, blob) for (ix, iy), blob in blobs.items()])
                cur.execute(q(GROW), (sum(map(len, blobs.values())), stream))

        self.db.write(tx, synced=False, fence=self.leases.fence(stream, epoch))

    def delete_stream(self, stream: str, *, epoch: int | None = None, also: tuple[str, ...] = ()) -> int:
        """Everything of a stream in this database gone (its trajectory, journal, cold tiles, lease, and the tables
        `also` names), fenced as a write; the poses deleted."""
        q = self.q

        def tx(cur):
            n = cur.execute(q("DELETE FROM poses WHERE stream = ?"), (stream,)).rowcount
            for table in ("journal", "cold_tiles", *also, "leases", "streams"):
                cur.execute(q(f"DELETE FROM {table} WHERE stream = ?"), (stream,))
            return n

        return self.db.write(tx, fence=self.leases.fence(stream, epoch))

    def sizes(self, stream: str, tables=(("poses", "pose"), ("journal", "frame"), ("cold_tiles", "block"))):
        """Rows and blob bytes per table of one stream (for stats and tests)."""
        out = {}
        for table, blob in tables:
            sql = f"SELECT COUNT(*), COALESCE(SUM(LENGTH({blob})), 0) FROM {table} WHERE stream = ?"
            n, b = self.db.read(sql, (stream,))[0]
            out[f"{table}_rows"], out[f"{table}_bytes"] = int(n), int(b)
        return out
