"""Durable state of the registration worker: an embedded SQLite file per deployment, one row set per stream.

Tables (they may share a file with the map service's map_streams/map_tiles, services/map_store.py):
  streams     stream, created, last_seq (last committed frame), snapshot_seq, client, bytes, last_write
  poses       (stream, seq): stamp, digest of the frame, status, pose (4x4 float64 bytes); every published pose
  snapshots   (in a second file, <name>.snapshots.sqlite) stream: the trajectory's `created`, seq, the OccVO
              state_dict after that frame (working map only); the latest one per stream
  journal     (stream, seq): the occupancy frames registered after the snapshot, to replay on resume
  cold_tiles  (stream, ix, iy, evicted_seq): map tiles evicted from the working set, with restored_seq once they came
              back. A restored row stays until the next snapshot: resuming from an older snapshot replays the frames
              that restored it and needs the block as it was.
  leases      stream: owner, fencing epoch, expires_at (services/sqlite_leases.py); writes given `epoch` check it in
              their transaction (services/store_api.py)

WAL journal (readers never block the writer), a busy timeout (another process may write the same file) and one
transaction per frame. synchronous=FULL by default: a pose is committed before it is published, and FULL makes that
commit survive a power cut too, not only a killed process (NORMAL does the latter; measured cost in services/README.md).

Snapshots have their own file because SQLite has one writer per file: a 100 MB snapshot written in the frames' file
held every stream's frame commit for up to a second. A snapshot counts only if its `created` is the stream's current
trajectory's and its seq is committed there; the journal and restored cold rows it covers are deleted only after it
is durable, so a crash between the two files' transactions leaves a valid (older) resume point.
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_services.array_pack import pack_arrays, unpack_arrays
from occvo_services.os_tuning import hold_priority, release_priority
from occvo_services.snapshot_file import SNAPSHOT_SCHEMA, SnapshotFile, snapshot_path
from occvo_services.sqlite_leases import LEASES_SCHEMA, SqliteLeases, fence
from occvo_services.sqlite_wal import checkpoint_loop, connect, transaction
from occvo_services.store_blobs import frame_digest, pack_frame, unpack_frame
from occvo_services.store_retention import COMMIT_USAGE, GROW, SqliteRetention, frame_bytes

__all__ = [  # importers of these names from here predate the split
    "frame_digest",
    "pack_arrays",
    "pack_frame",
    "snapshot_path",
    "unpack_arrays",
    "unpack_frame",
]


_LOG = logging.getLogger("occvo.registration.store")  # the worker's logger prints it

SCHEMA = (
    """
CREATE TABLE IF NOT EXISTS streams (
    stream       TEXT PRIMARY KEY,
    created      REAL NOT NULL,
    last_seq     INTEGER,
    snapshot_seq INTEGER,
    client       TEXT,  -- retention (services/store_retention.py): who wrote it last, its bytes, its last frame
    bytes        INTEGER NOT NULL DEFAULT 0,
    last_write   REAL
);
CREATE TABLE IF NOT EXISTS poses (
    stream TEXT NOT NULL,
    seq    INTEGER NOT NULL,
    stamp  REAL NOT NULL,
    digest BLOB NOT NULL,
    status TEXT NOT NULL,
    pose   BLOB NOT NULL,
    PRIMARY KEY (stream, seq)
) WITHOUT ROWID;
CREATE TABLE IF NOT EXISTS journal (
    stream TEXT NOT NULL,
    seq    INTEGER NOT NULL,
    frame  BLOB NOT NULL,
    PRIMARY KEY (stream, seq)
);
CREATE TABLE IF NOT EXISTS cold_tiles (
    stream       TEXT NOT NULL,
    ix           INTEGER NOT NULL,
    iy           INTEGER NOT NULL,
    evicted_seq  INTEGER NOT NULL,
    restored_seq INTEGER,
    block        BLOB NOT NULL,
    PRIMARY KEY (stream, ix, iy, evicted_seq)
);
"""
    + LEASES_SCHEMA
)
_PER_STREAM = ("poses", "journal", "cold_tiles")


@dataclass
class StoredPose:
    seq: int
    stamp: float
    digest: bytes
    status: str
    pose: np.ndarray  # 4x4


@dataclass
class StreamRecord:
    stream: str
    created: float
    last_seq: int | None
    snapshot_seq: int | None


class TrajectoryStore(SqliteLeases, SnapshotFile, SqliteRetention):
    """Two SQLite connections shared by the worker's stream lanes, each behind its lock: the frames' file and the
    snapshots' file (services/README.md). SQLite has one writer per file anyway."""

    def __init__(self, path: str | Path, synchronous: Literal["NORMAL", "FULL"] = "FULL", busy_timeout_s: float = 30.0):
        self.path, self.snapshot_path = str(path), snapshot_path(path)
        self.synchronous = synchronous
        self.db = connect(self.path, synchronous, busy_timeout_s, SCHEMA)
        # 64 kB pages for the snapshots' file: SQLite works per page and WAL frame, so a snapshot in 4 kB pages costs
        # several times the CPU; a file made with other pages keeps them
        self.snap_db = connect(self.snapshot_path, synchronous, busy_timeout_s, SNAPSHOT_SCHEMA, page_size=65536)
        self.lock, self.snap_lock = threading.Lock(), threading.Lock()
        self._writer_nice = os.getpriority(os.PRIO_PROCESS, 0)  # the opening thread's: _write_lock holds writers at it
        self._move_old_snapshots()
        self._add_snapshot_epochs()
        self._add_retention_columns()
        # reads on a connection of their own (WAL: a reader never waits for the writer): a restore reading megabytes
        # of cold tiles held every stream's commit behind the one connection's lock
        self.read_db = self.db if self.path == ":memory:" else connect(self.path, synchronous, busy_timeout_s, "")
        self.read_lock = self.lock if self.read_db is self.db else threading.Lock()
        self.measure_overhead()
        self._checkpointer = None
        if self.path != ":memory:":
            # the frames' WAL is copied into the file by a thread of its own, not by the commit that crosses SQLite's
            # autocheckpoint threshold: that commit held the store's lock, and every stream's commit behind it, for
            # the copy and its fsync (long beside a snapshot's flush with many streams)
            self.db.execute("PRAGMA wal_autocheckpoint=0")
            self._stop = threading.Event()
            self._checkpointer = threading.Thread(
                target=self._checkpoint_loop, args=(busy_timeout_s,), name="store-checkpointer", daemon=True
            )
            self._checkpointer.start()

    @staticmethod
    def open(url_or_path: str | Path, synchronous: str = "FULL"):
        """The store at a path, sqlite:///path or postgresql:// URL (services/store_api.open_store)."""
        from occvo_services.store_api import open_store

        return open_store(url_or_path, synchronous)

    CHECKPOINT_EVERY_S = 1.0
    WAL_BLOCK_PAGES = 65536  # a WAL this long (256 MB of 4 kB pages) after a pass: checkpoint it whole, writers waiting

    def _checkpoint_loop(self, busy_timeout_s: float) -> None:
        checkpoint_loop(self, busy_timeout_s)

    # -- transactions
    @contextlib.contextmanager
    def _write_lock(self, phases: dict | None = None):
        """The store's write lock, held at the priority of the thread that opened the store (the lanes'): a niced
        after-pose thread or snapshot writer holding it must not keep the lanes' commits waiting while other work
        takes the cores (priority ceiling; without it, on a shared host, most of a slow commit's time went to waiting for
        this lock)."""
        t0 = time.perf_counter()
        with self.lock:
            if phases is not None:
                phases["lock"] = (time.perf_counter() - t0) * 1000.0
            me = threading.get_native_id()
            held = hold_priority(me, self._writer_nice)
            try:
                yield
            finally:
                if held:
                    release_priority(me)

    def _write(self, fn, phases: dict | None = None):
        with self._write_lock(phases):
            return transaction(self.db, fn, phases)

    def _write_unsynced(self, fn):
        """A transaction whose loss in a power cut costs nothing (the next synced commit, WAL commits being ordered,
        or the resume's replay redoes it): no fsync of its own, so the other streams' commits wait less."""
        with self._write_lock():
            self.db.execute("PRAGMA synchronous=NORMAL")
            try:
                return transaction(self.db, fn)
            finally:
                self.db.execute(f"PRAGMA synchronous={self.synchronous}")

    def _read(self, sql: str, args=()) -> list:
        with self.read_lock:
            return self.read_db.execute(sql, args).fetchall()

    def ping(self) -> None:
        self._read("SELECT 1")

    # -- streams and poses
    def streams(self) -> list[str]:
        return [r[0] for r in self._read("SELECT stream FROM streams ORDER BY stream")]

    def record(self, stream: str) -> StreamRecord | None:
        rows = self._read("SELECT stream, created, last_seq, snapshot_seq FROM streams WHERE stream=?", (stream,))
        return StreamRecord(*rows[0]) if rows else None

    def pose(self, stream: str, seq: int) -> StoredPose | None:
        rows = self._read("SELECT seq, stamp, digest, status, pose FROM poses WHERE stream=? AND seq=?", (stream, seq))
        return _pose(rows[0]) if rows else None

    def poses(self, stream: str) -> list[StoredPose]:
        return [
            _pose(r)
            for r in self._read(
                "SELECT seq, stamp, digest, status, pose FROM poses WHERE stream=? ORDER BY seq", (stream,)
            )
        ]

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
        """One frame, atomically, before its pose is published: the pose and the journal entry. new_trajectory first
        drops everything of the stream. What the frame does to the map after that is finish_frame's. Returns where
        the time went, in ms: "lock" (this store's other writers), "begin" (other processes'), "commit". Given
        `epoch`, FencedError and nothing written if the stream's lease has moved on. `client`: whose the stream is now."""
        pose_bytes = np.ascontiguousarray(pose, np.float64).reshape(4, 4).tobytes()

        def tx(db):
            fence(db, stream, epoch, self.fenced_only)
            if new_trajectory:
                for table in _PER_STREAM:
                    db.execute(f"DELETE FROM {table} WHERE stream=?", (stream,))
                db.execute("INSERT OR REPLACE INTO streams (stream, created) VALUES (?, ?)", (stream, time.time()))
            elif db.execute("SELECT 1 FROM streams WHERE stream=?", (stream,)).fetchone() is None:
                db.execute("INSERT INTO streams (stream, created) VALUES (?, ?)", (stream, time.time()))
            db.execute(
                "INSERT OR REPLACE INTO poses VALUES (?, ?, ?, ?, ?, ?)",
                (stream, seq, float(stamp), digest, status, pose_bytes),
            )
            db.execute("INSERT OR REPLACE INTO journal VALUES (?, ?, ?)", (stream, seq, frame_blob))
            db.execute("UPDATE streams SET last_seq=? WHERE stream=?", (seq, stream))
            db.execute(COMMIT_USAGE, (time.time(), grown, new_trajectory, client, stream))

        grown = frame_bytes(digest, frame_blob)

        phases: dict[str, float] = {}
        self._write(tx, phases)
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
        ((ix, iy, evicted_seq)). A frame stopped before
        this is finished by the replay of the journal (the registration worker's resume), so this write need not
        reach the disk before the next one does: no sync of its own (WAL commits are ordered, so the next frame's
        synced commit carries it), one fsync a frame, not two."""

        def tx(db):
            fence(db, stream, epoch, self.fenced_only)
            if pose is not None:
                db.execute(
                    "UPDATE poses SET status='relocalised', pose=? WHERE stream=? AND seq=?",
                    (np.ascontiguousarray(pose, np.float64).reshape(4, 4).tobytes(), stream, seq),
                )
            db.executemany(
                "UPDATE cold_tiles SET restored_seq=? WHERE stream=? AND ix=? AND iy=? AND evicted_seq=?",
                [(seq, stream, ix, iy, e) for ix, iy, e in restored],
            )
            db.executemany(
                "INSERT OR REPLACE INTO cold_tiles VALUES (?, ?, ?, ?, NULL, ?)",
                [(stream, ix, iy, seq, blob) for (ix, iy), blob in blobs.items()],
            )
            if blobs:
                db.execute(GROW, (sum(map(len, blobs.values())), stream))

        blobs = {k: pack_arrays(b) for k, b in (evicted or {}).items()}  # before the lock
        self._write_unsynced(tx)

    def created(self, stream: str) -> float | None:
        """Identifies the stream's current trajectory (its creation time)."""
        rows = self._read("SELECT created FROM streams WHERE stream=?", (stream,))
        return rows[0][0] if rows else None

    def journal(self, stream: str, after_seq: int | None) -> list[tuple[int, OccupancyFrame]]:
        rows = self._read(
            "SELECT seq, frame FROM journal WHERE stream=? AND seq>? ORDER BY seq",
            (stream, -1 if after_seq is None else after_seq),
        )
        return [(int(s), unpack_frame(b)) for s, b in rows]

    # -- evicted map
    def cold_index(self, stream: str, as_of_seq: int | None = None) -> dict[tuple[int, int], list[int]]:
        """{(ix, iy): [evicted_seq, ...]} of the tiles out of the working set: now, or just after frame as_of_seq.
        (One block a tile, unless a frame reached into a tile already evicted.)"""
        if as_of_seq is None:
            rows = self._read(
                "SELECT ix, iy, evicted_seq FROM cold_tiles WHERE stream=? AND restored_seq IS NULL", (stream,)
            )
        else:
            rows = self._read(
                "SELECT ix, iy, evicted_seq FROM cold_tiles WHERE stream=? AND evicted_seq<=? "
                "AND (restored_seq IS NULL OR restored_seq>?)",
                (stream, as_of_seq, as_of_seq),
            )
        out: dict[tuple[int, int], list[int]] = {}
        for ix, iy, e in sorted(rows):
            out.setdefault((int(ix), int(iy)), []).append(int(e))
        return out

    def cold_block(self, stream: str, ix: int, iy: int, evicted_seq: int) -> bytes:
        rows = self._read(
            "SELECT block FROM cold_tiles WHERE stream=? AND ix=? AND iy=? AND evicted_seq=?",
            (stream, ix, iy, evicted_seq),
        )
        if not rows:
            raise KeyError(f"stream {stream}: no cold tile {ix},{iy} evicted at seq {evicted_seq}")
        return rows[0][0]

    def delete_stream(self, stream: str, *, epoch: int | None = None) -> int:
        """Everything of a stream gone: trajectory, journal, cold tiles, lease, snapshot (`occvo store delete`; a
        worker's, fenced); the poses deleted. Its workers must not serve it meanwhile (their state would write it back)."""

        def tx(db):
            fence(db, stream, epoch, self.fenced_only)
            n = db.execute("DELETE FROM poses WHERE stream=?", (stream,)).rowcount
            for table in ("journal", "cold_tiles", "leases", "streams"):
                db.execute(f"DELETE FROM {table} WHERE stream=?", (stream,))
            return n

        n = self._write(tx)
        with self.snap_lock:
            transaction(self.snap_db, lambda db: db.execute("DELETE FROM snapshots WHERE stream=?", (stream,)))
        return n

    def sizes(self, stream: str) -> dict[str, int]:
        """Rows and blob bytes per table of one stream (for stats and tests)."""
        out = {}
        for table, blob in (("poses", "pose"), ("snapshots", "state"), ("journal", "frame"), ("cold_tiles", "block")):
            sql = f"SELECT COUNT(*), COALESCE(SUM(LENGTH({blob})), 0) FROM {table} WHERE stream=?"
            if table == "snapshots":
                with self.snap_lock:
                    n, b = self.snap_db.execute(sql, (stream,)).fetchone()
            else:
                n, b = self._read(sql, (stream,))[0]
            out[f"{table}_rows"], out[f"{table}_bytes"] = int(n), int(b)
        return out

    def close(self) -> None:
        if self._checkpointer is not None:
            self._stop.set()
            self._checkpointer.join()
        with self.lock, self.snap_lock:
            if self.read_db is not self.db:
                with self.read_lock:
                    self.read_db.close()
            self.db.close()
            self.snap_db.close()

    def file_sizes_mb(self) -> dict[str, float]:
        """Sizes of the SQLite files and their WALs, MB (for logs)."""
        paths = {
            "db_mb": Path(self.path),
            "wal_mb": Path(f"{self.path}-wal"),
            "snapshots_mb": Path(self.snapshot_path),
            "snapshots_wal_mb": Path(f"{self.snapshot_path}-wal"),
        }
        # an in-memory store has neither file, a checkpointed WAL may be gone: only what exists is reported
        return {name: round(path.stat().st_size / 2**20, 1) for name, path in paths.items() if path.is_file()}


def _pose(row) -> StoredPose:
    seq, stamp, digest, status, blob = row
    return StoredPose(
        int(seq), float(stamp), bytes(digest), status, np.frombuffer(blob, np.float64).reshape(4, 4).copy()
    )
