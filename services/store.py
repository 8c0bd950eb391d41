"""Durable state of the registration worker: an embedded SQLite file per deployment, one row set per stream.

Tables (they may share a file with the map service's map_streams/map_tiles, services/map_store.py):
  streams     stream, created, last_seq (last committed frame), snapshot_seq
  poses       (stream, seq): stamp, digest of the frame, status, pose (4x4 float64 bytes); every published pose
  snapshots   stream: seq, the OccVO state_dict after that frame (working map only); the latest one per stream
  journal     (stream, seq): the occupancy frames registered after the snapshot, to replay on resume
  cold_tiles  (stream, ix, iy, evicted_seq): map tiles evicted from the working set, with restored_seq once they came
              back. A restored row stays until the next snapshot: resuming from an older snapshot replays the frames
              that restored it and needs the block as it was.

WAL journal (readers never block the writer), a busy timeout (another process may write the same file) and one
transaction per frame. synchronous=FULL by default: a pose is committed before it is published, and FULL makes that
commit survive a power cut too, not only a killed process (NORMAL does the latter; measured cost in services/README.md).
"""

from __future__ import annotations

import hashlib
import io
import sqlite3
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Literal

import numpy as np

from occvo_core.errors import ConfigError
from occvo_core.frame import OccupancyFrame

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
CREATE TABLE IF NOT EXISTS snapshots (
    stream TEXT PRIMARY KEY,
    seq    INTEGER NOT NULL,
    state  BLOB NOT NULL
);
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
_PER_STREAM = ("poses", "snapshots", "journal", "cold_tiles")


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
    return pack_arrays({"points": frame.points, "labels": frame.labels, "index": np.int64(frame.index),
                        "stamp": np.float64(frame.stamp)})


def unpack_frame(blob: bytes) -> OccupancyFrame:
    a = unpack_arrays(blob)
    return OccupancyFrame(a["points"], a["labels"], index=int(a["index"]), stamp=float(a["stamp"]))


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
    """One SQLite connection shared by the worker's stream lanes (SQLite has one writer anyway), behind a lock."""

    def __init__(self, path: str | Path, synchronous: Literal["NORMAL", "FULL"] = "FULL", busy_timeout_s: float = 30.0):
        self.path = str(path)
        try:
            if self.path != ":memory:":
                Path(self.path).parent.mkdir(parents=True, exist_ok=True)
            self.db = sqlite3.connect(self.path, timeout=busy_timeout_s, isolation_level=None, check_same_thread=False)
            self.db.execute("PRAGMA journal_mode=WAL")
            self.db.execute(f"PRAGMA synchronous={synchronous}")
            self.db.execute(f"PRAGMA busy_timeout={int(busy_timeout_s * 1000)}")
            self.db.execute("PRAGMA journal_size_limit=67108864")  # snapshots are big: truncate the WAL after checkpoints
            self.db.executescript(SCHEMA)
        except sqlite3.Error as exc:
            raise ConfigError(f"trajectory store {self.path}: {exc}") from None
        self.lock = threading.Lock()

    # -- transactions
    def _write(self, fn):
        with self.lock:
            self.db.execute("BEGIN IMMEDIATE")
            try:
                out = fn(self.db)
            except BaseException:
                self.db.execute("ROLLBACK")
                raise
            self.db.execute("COMMIT")
            return out

    def _read(self, sql: str, args=()) -> list:
        with self.lock:
            return self.db.execute(sql, args).fetchall()

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
        return [_pose(r) for r in self._read("SELECT seq, stamp, digest, status, pose FROM poses WHERE stream=? ORDER BY seq", (stream,))]

    def commit_frame(self, stream: str, seq: int, stamp: float, digest: bytes, status: str, pose: np.ndarray,
                     frame_blob: bytes, new_trajectory: bool = False, evicted: dict | None = None,
                     restored: Iterable[tuple[int, int, int]] = ()) -> None:
        """One frame, atomically: its pose, its journal entry, the tiles it evicted ({(ix, iy): block bytes}) and the
        cold rows it restored ((ix, iy, evicted_seq)). new_trajectory first drops everything of the stream."""
        pose_bytes = np.ascontiguousarray(pose, np.float64).reshape(4, 4).tobytes()

        def tx(db):
            if new_trajectory:
                for table in _PER_STREAM:
                    db.execute(f"DELETE FROM {table} WHERE stream=?", (stream,))
                db.execute("INSERT OR REPLACE INTO streams VALUES (?, ?, NULL, NULL)", (stream, time.time()))
            elif db.execute("SELECT 1 FROM streams WHERE stream=?", (stream,)).fetchone() is None:
                db.execute("INSERT INTO streams VALUES (?, ?, NULL, NULL)", (stream, time.time()))
            db.execute("INSERT OR REPLACE INTO poses VALUES (?, ?, ?, ?, ?, ?)",
                       (stream, seq, float(stamp), digest, status, pose_bytes))
            db.execute("INSERT OR REPLACE INTO journal VALUES (?, ?, ?)", (stream, seq, frame_blob))
            db.executemany("UPDATE cold_tiles SET restored_seq=? WHERE stream=? AND ix=? AND iy=? AND evicted_seq=?",
                           [(seq, stream, ix, iy, e) for ix, iy, e in restored])
            db.executemany("INSERT OR REPLACE INTO cold_tiles VALUES (?, ?, ?, ?, NULL, ?)",
                           [(stream, ix, iy, seq, blob) for (ix, iy), blob in (evicted or {}).items()])
            db.execute("UPDATE streams SET last_seq=? WHERE stream=?", (seq, stream))

        self._write(tx)

    # -- snapshots and journal
    def write_snapshot(self, stream: str, seq: int, state: dict[str, np.ndarray] | bytes) -> None:
        """The state after frame `seq` (arrays, or pack_arrays' bytes) replaces the older snapshot; the journal up to
        it and the cold rows restored by then are no longer needed. Arrays are written into the row in place
        (Python >= 3.11): packing them first would hold a copy of the whole state, and the worker's peak RSS with it."""
        in_place = hasattr(sqlite3.Connection, "blobopen")
        if isinstance(state, dict) and not in_place:
            state = pack_arrays(state)
        write = (lambda fp: _savez(fp, state)) if isinstance(state, dict) else (lambda fp: fp.write(state))
        size = _BlobFile()
        write(size)

        def tx(db):
            if in_place:
                rowid = db.execute("INSERT OR REPLACE INTO snapshots VALUES (?, ?, zeroblob(?))",
                                   (stream, seq, size.size)).lastrowid
                with db.blobopen("snapshots", "state", rowid) as blob:
                    write(_BlobFile(blob))
            else:
                db.execute("INSERT OR REPLACE INTO snapshots VALUES (?, ?, ?)", (stream, seq, state))
            db.execute("DELETE FROM journal WHERE stream=? AND seq<=?", (stream, seq))
            db.execute("DELETE FROM cold_tiles WHERE stream=? AND restored_seq IS NOT NULL AND restored_seq<=?", (stream, seq))
            db.execute("UPDATE streams SET snapshot_seq=? WHERE stream=?", (seq, stream))

        self._write(tx)

    def snapshot(self, stream: str) -> tuple[int, bytes] | None:
        rows = self._read("SELECT seq, state FROM snapshots WHERE stream=?", (stream,))
        return (int(rows[0][0]), rows[0][1]) if rows else None

    def journal(self, stream: str, after_seq: int | None) -> list[tuple[int, OccupancyFrame]]:
        rows = self._read("SELECT seq, frame FROM journal WHERE stream=? AND seq>? ORDER BY seq",
                          (stream, -1 if after_seq is None else after_seq))
        return [(int(s), unpack_frame(b)) for s, b in rows]

    # -- evicted map
    def cold_index(self, stream: str, as_of_seq: int | None = None) -> dict[tuple[int, int], list[int]]:
        """{(ix, iy): [evicted_seq, ...]} of the tiles out of the working set: now, or just after frame as_of_seq.
        (One block a tile, unless a frame reached into a tile already evicted.)"""
        if as_of_seq is None:
            rows = self._read("SELECT ix, iy, evicted_seq FROM cold_tiles WHERE stream=? AND restored_seq IS NULL", (stream,))
        else:
            rows = self._read("SELECT ix, iy, evicted_seq FROM cold_tiles WHERE stream=? AND evicted_seq<=? "
                              "AND (restored_seq IS NULL OR restored_seq>?)", (stream, as_of_seq, as_of_seq))
        out: dict[tuple[int, int], list[int]] = {}
        for ix, iy, e in sorted(rows):
            out.setdefault((int(ix), int(iy)), []).append(int(e))
        return out

    def cold_block(self, stream: str, ix: int, iy: int, evicted_seq: int) -> bytes:
        rows = self._read("SELECT block FROM cold_tiles WHERE stream=? AND ix=? AND iy=? AND evicted_seq=?",
                          (stream, ix, iy, evicted_seq))
        if not rows:
            raise KeyError(f"stream {stream}: no cold tile {ix},{iy} evicted at seq {evicted_seq}")
        return rows[0][0]

    def sizes(self, stream: str) -> dict[str, int]:
        """Rows and blob bytes per table of one stream (for stats and tests)."""
        out = {}
        for table, blob in (("poses", "pose"), ("snapshots", "state"), ("journal", "frame"), ("cold_tiles", "block")):
            n, b = self._read(f"SELECT COUNT(*), COALESCE(SUM(LENGTH({blob})), 0) FROM {table} WHERE stream=?", (stream,))[0]
            out[f"{table}_rows"], out[f"{table}_bytes"] = int(n), int(b)
        return out

    def close(self) -> None:
        with self.lock:
            self.db.close()

    def file_sizes_mb(self) -> dict[str, float]:
        """Sizes of the SQLite file and its WAL, MB (for logs)."""
        paths = {"db_mb": Path(self.path), "wal_mb": Path(f"{self.path}-wal")}
        # an in-memory store has neither file, a checkpointed WAL may be gone: only what exists is reported
        return {name: round(path.stat().st_size / 2**20, 1) for name, path in paths.items() if path.is_file()}


def _pose(row) -> StoredPose:
    seq, stamp, digest, status, blob = row
    return StoredPose(int(seq), float(stamp), bytes(digest), status, np.frombuffer(blob, np.float64).reshape(4, 4).copy())
