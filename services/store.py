"""Durable state of the registration worker: an embedded SQLite file per deployment, one row set per stream.

Tables (they may share a file with the map service's map_streams/map_tiles, services/map_store.py):
  streams     stream, created, last_seq (last committed frame), snapshot_seq
  poses       (stream, seq): stamp, digest of the frame, status, pose (4x4 float64 bytes); every published pose
  snapshots   (in a second file, <name>.snapshots.sqlite) stream: the trajectory's `created`, seq, the OccVO
              state_dict after that frame (working map only); the latest one per stream
  journal     (stream, seq): the occupancy frames registered after the snapshot, to replay on resume
  cold_tiles  (stream, ix, iy, evicted_seq): map tiles evicted from the working set, with restored_seq once they came
              back. A restored row stays until the next snapshot: resuming from an older snapshot replays the frames
              that restored it and needs the block as it was.

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
import hashlib
import io
import logging
import os
import sqlite3
import threading
import time
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from occvo_core.errors import ConfigError
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID
from services.runtime import hold_priority, log_event, lower_priority, name_os_thread, release_priority
from services.sqlite_wal import enable_wal

_LOG = logging.getLogger("occvo.registration.store")  # the worker's logger prints it

SCHEMA = """
CREATE TABLE IF NOT EXISTS streams (
    stream       TEXT PRIMARY KEY,
    created      REAL NOT NULL,
    last_seq     INTEGER,
    snapshot_seq INTEGER
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
SNAPSHOT_SCHEMA = """
CREATE TABLE IF NOT EXISTS snapshots (
    stream  TEXT PRIMARY KEY,
    created REAL NOT NULL,
    seq     INTEGER NOT NULL,
    state   BLOB NOT NULL
);
"""
_PER_STREAM = ("poses", "journal", "cold_tiles")


def snapshot_path(path: str | Path) -> str:
    """The snapshot file beside a store file: var/occvo.sqlite -> var/occvo.snapshots.sqlite."""
    path = str(path)
    if path == ":memory:":
        return path
    p = Path(path)
    return str(p.with_name(f"{p.stem}.snapshots{p.suffix or '.sqlite'}"))


def pack_arrays(arrays: dict[str, np.ndarray]) -> bytes:
    """numpy arrays -> .npz bytes (no pickle, no compression: the blobs are read back whole and soon)."""
    buf = io.BytesIO()
    _savez(buf, arrays)
    return buf.getvalue()


class _BlobFile(io.RawIOBase):
    """A seekable file over a fixed-size SQLite blob, for np.savez to write into; with blob=None it only measures
    how many bytes would be written. The same arrays give the same bytes, so a measuring pass sizes the blob."""

    def __init__(self, blob=None):
        super().__init__()
        self.blob, self.pos, self.size = blob, 0, 0

    def writable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return True

    def tell(self) -> int:
        return self.pos

    def seek(self, offset: int, whence: int = io.SEEK_SET) -> int:
        self.pos = {io.SEEK_SET: 0, io.SEEK_CUR: self.pos, io.SEEK_END: self.size}[whence] + offset
        return self.pos

    def write(self, data) -> int:
        n = memoryview(data).nbytes
        if self.blob is not None:
            self.blob.seek(self.pos)
            self.blob.write(data)
        self.pos += n
        self.size = max(self.size, self.pos)
        return n


def _savez(fp, arrays: dict[str, np.ndarray]) -> None:
    np.savez(fp, **{k: np.asarray(v) for k, v in arrays.items()})


def unpack_arrays(blob: bytes) -> dict[str, np.ndarray]:
    with np.load(io.BytesIO(blob), allow_pickle=False) as z:
        return {k: z[k] for k in z.files}


def frame_digest(points: np.ndarray, labels: np.ndarray, stamp: float) -> bytes:
    """What identifies a frame for idempotent resends: its stamp and its exact content."""
    h = hashlib.blake2b(digest_size=16)
    h.update(np.float64(stamp).tobytes())
    h.update(np.ascontiguousarray(points, np.float64).tobytes())
    h.update(np.ascontiguousarray(labels, np.uint8).tobytes())
    return h.digest()


def pack_frame(frame: OccupancyFrame) -> bytes:
    """A journal entry. Frames on the Occ3D grid (what the workers send: voxel indices) are kept as uint8 indices,
    3 bytes a voxel instead of 24: the journal is most of what the store writes, and its WAL checkpoints held every
    stream's commit. Exact: used only when the grid's centres give back the very same coordinates."""
    head = {"labels": frame.labels, "index": np.int64(frame.index), "stamp": np.float64(frame.stamp)}
    points = np.asarray(frame.points, np.float64)
    ijk = OCC3D_GRID.indices_of(points)
    if OCC3D_GRID.inside(ijk).all() and np.array_equal(OCC3D_GRID.centres_of(ijk), points):
        return pack_arrays({"ijk": ijk.astype(np.uint8), **head})
    return pack_arrays({"points": points, **head})


def unpack_frame(blob: bytes) -> OccupancyFrame:
    a = unpack_arrays(blob)
    points = OCC3D_GRID.centres_of(a["ijk"].astype(np.int64)) if "ijk" in a else a["points"]
    return OccupancyFrame(points, a["labels"], index=int(a["index"]), stamp=float(a["stamp"]))


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


class TrajectoryStore:
    """Two SQLite connections shared by the worker's stream lanes, each behind its lock: the frames' file and the
    snapshots' file (services/README.md). SQLite has one writer per file anyway."""

    def __init__(self, path: str | Path, synchronous: Literal["NORMAL", "FULL"] = "FULL", busy_timeout_s: float = 30.0):
        self.path, self.snapshot_path = str(path), snapshot_path(path)
        self.synchronous = synchronous
        self.db = _connect(self.path, synchronous, busy_timeout_s, SCHEMA)
        # 64 kB pages for the snapshots' file: a 50 MB snapshot written in 4 kB pages cost 170 ms of CPU (SQLite's
        # work per page and WAL frame), in 64 kB pages 60 ms; a file made with other pages keeps them
        self.snap_db = _connect(self.snapshot_path, synchronous, busy_timeout_s, SNAPSHOT_SCHEMA, page_size=65536)
        self.lock, self.snap_lock = threading.Lock(), threading.Lock()
        self._writer_nice = os.getpriority(os.PRIO_PROCESS, 0)  # the opening thread's: _write_lock holds writers at it
        self._move_old_snapshots()
        # reads on a connection of their own (WAL: a reader never waits for the writer): a restore reading megabytes
        # of cold tiles held every stream's commit behind the one connection's lock
        self.read_db = self.db if self.path == ":memory:" else _connect(self.path, synchronous, busy_timeout_s, "")
        self.read_lock = self.lock if self.read_db is self.db else threading.Lock()
        self._checkpointer = None
        if self.path != ":memory:":
            # the frames' WAL is copied into the file by a thread of its own, not by the commit that crosses SQLite's
            # autocheckpoint threshold: that commit held the store's lock, and every stream's commit behind it, for
            # the copy and its fsync (70 to 200 ms beside a snapshot's flush, eight streams)
            self.db.execute("PRAGMA wal_autocheckpoint=0")
            self._stop = threading.Event()
            self._checkpointer = threading.Thread(
                target=self._checkpoint_loop, args=(busy_timeout_s,), name="store-checkpointer", daemon=True
            )
            self._checkpointer.start()

    CHECKPOINT_EVERY_S = 1.0
    WAL_BLOCK_PAGES = 65536  # a WAL this long (256 MB of 4 kB pages) after a pass: checkpoint it whole, writers waiting

    def _checkpoint_loop(self, busy_timeout_s: float) -> None:
        """PASSIVE checkpoints (they copy what no reader needs and never wait for a writer) every second, on their own
        connection; the next commit after a complete one starts the WAL over."""
        db = _connect(self.path, self.synchronous, busy_timeout_s, "")
        _background_thread("store-checkpoint")
        failing = False
        try:
            while not self._stop.wait(self.CHECKPOINT_EVERY_S):
                try:
                    _, log_pages, _ = db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
                    if log_pages >= self.WAL_BLOCK_PAGES:
                        db.execute("PRAGMA wal_checkpoint(RESTART)")
                    failing = False
                except sqlite3.Error as exc:  # busy or an I/O error: the next pass tries again; said once a run of them
                    if not failing:
                        log_event(
                            _LOG,
                            "WAL checkpoint failed; retrying every pass (the WAL grows meanwhile)",
                            logging.WARNING,
                            path=self.path,
                            error=repr(exc),
                        )
                    failing = True
        finally:
            db.close()

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
            _transaction(
                self.snap_db,
                lambda snap: snap.executemany("INSERT OR REPLACE INTO snapshots VALUES (?, ?, ?, ?)", rows),
            )
            db.execute("DROP TABLE snapshots")

        if old_table(self.db):  # an open takes no write lock otherwise
            _transaction(self.db, tx)

    # -- transactions
    @contextlib.contextmanager
    def _write_lock(self, phases: dict | None = None):
        """The store's write lock, held at the priority of the thread that opened the store (the lanes'): a niced
        after-pose thread or snapshot writer holding it must not keep the lanes' commits waiting while other work
        takes the cores (priority ceiling; in session 21's shared-host runs, 70% of the time of commits over
        100 ms went to waiting for this lock)."""
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
            return _transaction(self.db, fn, phases)

    def _write_unsynced(self, fn):
        """A transaction whose loss in a power cut costs nothing (the next synced commit, WAL commits being ordered,
        or the resume's replay redoes it): no fsync of its own, so the other streams' commits wait less."""
        with self._write_lock():
            self.db.execute("PRAGMA synchronous=NORMAL")
            try:
                return _transaction(self.db, fn)
            finally:
                self.db.execute(f"PRAGMA synchronous={self.synchronous}")

    def _read(self, sql: str, args=()) -> list:
        with self.read_lock:
            return self.read_db.execute(sql, args).fetchall()

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
    ) -> dict[str, float]:
        """One frame, atomically, before its pose is published: the pose and the journal entry. new_trajectory first
        drops everything of the stream. What the frame does to the map after that is finish_frame's. Returns where
        the time went, in ms: "lock" (this store's other writers), "begin" (other processes'), "commit"."""
        pose_bytes = np.ascontiguousarray(pose, np.float64).reshape(4, 4).tobytes()

        def tx(db):
            if new_trajectory:
                for table in _PER_STREAM:
                    db.execute(f"DELETE FROM {table} WHERE stream=?", (stream,))
                db.execute("INSERT OR REPLACE INTO streams VALUES (?, ?, NULL, NULL)", (stream, time.time()))
            elif db.execute("SELECT 1 FROM streams WHERE stream=?", (stream,)).fetchone() is None:
                db.execute("INSERT INTO streams VALUES (?, ?, NULL, NULL)", (stream, time.time()))
            db.execute(
                "INSERT OR REPLACE INTO poses VALUES (?, ?, ?, ?, ?, ?)",
                (stream, seq, float(stamp), digest, status, pose_bytes),
            )
            db.execute("INSERT OR REPLACE INTO journal VALUES (?, ?, ?)", (stream, seq, frame_blob))
            db.execute("UPDATE streams SET last_seq=? WHERE stream=?", (seq, stream))

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
    ) -> None:
        """What a committed frame did after its pose was published, atomically: its relocalised pose (a loop
        closed; status "relocalised"), the tiles it evicted ({(ix, iy): block arrays}) and the cold rows it restored
        ((ix, iy, evicted_seq)). A frame stopped before
        this is finished by the replay of the journal (the registration worker's resume), so this write need not
        reach the disk before the next one does: no sync of its own (WAL commits are ordered, so the next frame's
        synced commit carries it), one fsync a frame, not two."""

        def tx(db):
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

        blobs = {k: pack_arrays(b) for k, b in (evicted or {}).items()}  # before the lock
        self._write_unsynced(tx)

    # -- snapshots and journal
    def write_snapshot(
        self, stream: str, seq: int, state: dict[str, np.ndarray] | bytes, created: float | None = None
    ) -> bool:
        """The state after frame `seq` (arrays, or pack_arrays' bytes) replaces the older snapshot; then the journal
        up to it and the cold rows restored by then go. Arrays are written into the row in place (Python >= 3.11):
        packing them first would hold a copy of the whole state, and the worker's peak RSS with it. Frame commits
        go on meanwhile (another file). `created`: the trajectory the state belongs to (created(stream) when the state
        was taken), by default the current one. False, and the journal kept, if the stream started another since."""
        created = self.created(stream) if created is None else created
        if created is None:
            return False
        in_place = hasattr(sqlite3.Connection, "blobopen")
        if isinstance(state, dict) and not in_place:
            state = pack_arrays(state)
        write = (lambda fp: _savez(fp, state)) if isinstance(state, dict) else (lambda fp: fp.write(state))
        size = _BlobFile()
        write(size)

        def snap_tx(db):
            if in_place:
                rowid = db.execute(
                    "INSERT OR REPLACE INTO snapshots VALUES (?, ?, ?, zeroblob(?))", (stream, created, seq, size.size)
                ).lastrowid
                with db.blobopen("snapshots", "state", rowid) as blob:
                    write(_BlobFile(blob))
            else:
                db.execute("INSERT OR REPLACE INTO snapshots VALUES (?, ?, ?, ?)", (stream, created, seq, state))

        with self.snap_lock:
            _transaction(self.snap_db, snap_tx)

        def tx(db):  # only if the trajectory is still the one snapshotted
            if db.execute("SELECT created FROM streams WHERE stream=?", (stream,)).fetchone() != (created,):
                return False
            db.execute("DELETE FROM journal WHERE stream=? AND seq<=?", (stream, seq))
            db.execute(
                "DELETE FROM cold_tiles WHERE stream=? AND restored_seq IS NOT NULL AND restored_seq<=?", (stream, seq)
            )
            db.execute("UPDATE streams SET snapshot_seq=? WHERE stream=?", (seq, stream))
            return True

        return self._write_unsynced(tx)  # lost in a power cut, the rows go with the next snapshot

    def drop_old_snapshots(self, stream: str) -> int:
        """Delete the stream's snapshot of a trajectory it no longer has (a reset started another): never read again,
        5 MB or more each. Returns the rows deleted."""
        created = self.created(stream)
        with self.snap_lock:
            return _transaction(
                self.snap_db,
                lambda db: (
                    db.execute("DELETE FROM snapshots WHERE stream=? AND created IS NOT ?", (stream, created)).rowcount
                ),
            )

    def created(self, stream: str) -> float | None:
        """Identifies the stream's current trajectory (its creation time)."""
        rows = self._read("SELECT created FROM streams WHERE stream=?", (stream,))
        return rows[0][0] if rows else None

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


def _background_thread(name: str, nice: int = 10) -> None:
    """Name the calling OS thread and run it below the threads that commit poses (best effort)."""
    name_os_thread(name)
    lower_priority(nice)


def _connect(
    path: str, synchronous: str, busy_timeout_s: float, schema: str, page_size: int | None = None
) -> sqlite3.Connection:
    try:
        if path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        db = sqlite3.connect(path, timeout=busy_timeout_s, isolation_level=None, check_same_thread=False)
        if page_size:
            db.execute(f"PRAGMA page_size={int(page_size)}")  # only a new file takes it, and only before WAL mode
        enable_wal(db, busy_timeout_s)
        db.execute(f"PRAGMA synchronous={synchronous}")
        db.execute(f"PRAGMA busy_timeout={int(busy_timeout_s * 1000)}")
        db.execute("PRAGMA journal_size_limit=67108864")  # snapshots are big: truncate the WAL after checkpoints
        if schema:
            db.executescript(schema)
    except sqlite3.Error as exc:
        raise ConfigError(f"trajectory store {path}: {exc}") from None
    return db


def _transaction(db: sqlite3.Connection, fn, phases: dict | None = None):
    """fn(db) in one write transaction. phases, if given, gets the ms spent waiting for the file's write lock
    ("begin": another connection or process writing) and committing ("commit": the WAL write and its sync)."""
    t0 = time.perf_counter()
    db.execute("BEGIN IMMEDIATE")
    t1 = time.perf_counter()
    try:
        out = fn(db)
    except BaseException:
        db.execute("ROLLBACK")
        raise
    t2 = time.perf_counter()
    db.execute("COMMIT")
    if phases is not None:
        phases["begin"], phases["commit"] = (t1 - t0) * 1000.0, (time.perf_counter() - t2) * 1000.0
    return out


def _pose(row) -> StoredPose:
    seq, stamp, digest, status, blob = row
    return StoredPose(
        int(seq), float(stamp), bytes(digest), status, np.frombuffer(blob, np.float64).reshape(4, 4).copy()
    )
