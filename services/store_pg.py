"""The registration worker's store in PostgreSQL: what services/store.py keeps in SQLite files (streams, poses,
journal, cold tiles, snapshots), plus the streams' leases, in one database that workers on many hosts share.

Durability as in SQLite: a commit_frame that returned is durable (synchronous_commit on; the server runs with fsync);
the writes whose loss the resume redoes (finish_frame, a snapshot's journal cleanup) commit asynchronously, and the
next synchronous commit carries them (the WAL is flushed in order). Fencing: a write given `epoch` locks the stream's
lease row (FOR SHARE) in its own transaction and writes nothing if the lease's epoch moved on (FencedError); a
takeover (acquire) waits for those writes and they for it. Lease expiry uses the server's clock (now()), so the hosts'
clocks do not matter. Snapshots carry the epoch they were written under and never replace one of a later epoch."""

from __future__ import annotations

import struct
import time
from collections.abc import Iterable

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_services.array_pack import chunks, layout, pack_arrays
from occvo_services.pg_leases import PgLeases
from occvo_services.pg_pool import PgPool
from occvo_services.store import StoredPose, StreamRecord, _pose
from occvo_services.store_api import FencedError, StoreUnavailable
from occvo_services.store_blobs import unpack_frame
from occvo_services.store_retention import COMMIT_USAGE, GROW, PG_RETENTION_SCHEMA, PgRetention, frame_bytes

# blobs are stored as they are (STORAGE EXTERNAL): compressing a frame or a snapshot costs CPU in the commit's path
SCHEMA = """
CREATE TABLE IF NOT EXISTS streams (
    stream       TEXT PRIMARY KEY,
    created      DOUBLE PRECISION NOT NULL,
    last_seq     BIGINT,
    snapshot_seq BIGINT
);
CREATE TABLE IF NOT EXISTS poses (
    stream TEXT NOT NULL,
    seq    BIGINT NOT NULL,
    stamp  DOUBLE PRECISION NOT NULL,
    digest BYTEA NOT NULL,
    status TEXT NOT NULL,
    pose   BYTEA NOT NULL,
    PRIMARY KEY (stream, seq)
);
CREATE TABLE IF NOT EXISTS journal (
    stream TEXT NOT NULL,
    seq    BIGINT NOT NULL,
    frame  BYTEA NOT NULL,
    PRIMARY KEY (stream, seq)
);
ALTER TABLE journal ALTER COLUMN frame SET STORAGE EXTERNAL;
CREATE TABLE IF NOT EXISTS cold_tiles (
    stream       TEXT NOT NULL,
    ix           INTEGER NOT NULL,
    iy           INTEGER NOT NULL,
    evicted_seq  BIGINT NOT NULL,
    restored_seq BIGINT,
    block        BYTEA NOT NULL,
    PRIMARY KEY (stream, ix, iy, evicted_seq)
);
ALTER TABLE cold_tiles ALTER COLUMN block SET STORAGE EXTERNAL;
CREATE TABLE IF NOT EXISTS snapshots (
    stream  TEXT PRIMARY KEY,
    created DOUBLE PRECISION NOT NULL,
    seq     BIGINT NOT NULL,
    epoch   BIGINT,
    state   BYTEA NOT NULL
);
ALTER TABLE snapshots ALTER COLUMN state SET STORAGE EXTERNAL;
CREATE TABLE IF NOT EXISTS leases (
    stream     TEXT PRIMARY KEY,
    owner      TEXT,
    epoch      BIGINT NOT NULL,
    expires_at TIMESTAMPTZ NOT NULL
);
"""
SCHEMA += PG_RETENTION_SCHEMA  # a database made before retention gets its columns
_PER_STREAM = ("poses", "journal", "cold_tiles")
_COPY_HEAD = b"PGCOPY\n\xff\r\n\x00" + struct.pack("!ii", 0, 0)


def _field(data: bytes) -> bytes:
    return struct.pack("!i", len(data)) + data


class PgTrajectoryStore(PgLeases, PgRetention):
    """TrajectoryStore's methods (services/store_api.Store) on a PostgreSQL database, by URL."""

    def __init__(self, url: str, synchronous: str = "FULL", pool_size: int = 4):
        self.path = url  # what the worker logs: the pool redacts it where it names the store
        self.synchronous = synchronous
        self.pool = PgPool(url, pool_size, "trajectory store", SCHEMA)
        self.label = self.pool.label
        # NORMAL (store_sync "normal"): frame commits asynchronous too, a server crash may lose the last ones
        self._frame_commit = "on" if synchronous.upper() == "FULL" else "off"

    def _read(self, sql: str, args=(), binary: bool = False) -> list:
        return self.pool.run(lambda conn: conn.execute(sql, args, binary=binary).fetchall())

    def ping(self) -> None:
        self._read("SELECT 1")  # StoreUnavailable while the server is away

    # -- streams and poses
    def streams(self) -> list[str]:
        return [r[0] for r in self._read("SELECT stream FROM streams ORDER BY stream")]

    def record(self, stream: str) -> StreamRecord | None:
        rows = self._read("SELECT stream, created, last_seq, snapshot_seq FROM streams WHERE stream = %s", (stream,))
        return StreamRecord(*rows[0]) if rows else None

    def created(self, stream: str) -> float | None:
        rows = self._read("SELECT created FROM streams WHERE stream = %s", (stream,))
        return rows[0][0] if rows else None

    def pose(self, stream: str, seq: int) -> StoredPose | None:
        rows = self._read(
            "SELECT seq, stamp, digest, status, pose FROM poses WHERE stream = %s AND seq = %s", (stream, seq), True
        )
        return _pose(rows[0]) if rows else None

    def poses(self, stream: str) -> list[StoredPose]:
        sql = "SELECT seq, stamp, digest, status, pose FROM poses WHERE stream = %s ORDER BY seq"
        return [_pose(r) for r in self._read(sql, (stream,), True)]

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
        """One frame, atomically and durably, before its pose is published (TrajectoryStore.commit_frame). Returns
        where the time went, ms: "lock" (waiting for a connection), "begin" (the lease, or a takeover holding it),
        "commit"."""
        pose_bytes = np.ascontiguousarray(pose, np.float64).reshape(4, 4).tobytes()
        phases: dict[str, float] = {}
        grown = frame_bytes(digest, frame_blob)

        def tx(conn):
            t0 = time.perf_counter()
            with conn.transaction():
                if self._frame_commit == "off":
                    conn.execute("SET LOCAL synchronous_commit = off")
                self._fence(conn, stream, epoch)
                t1 = time.perf_counter()
                if new_trajectory:
                    for table in _PER_STREAM:
                        conn.execute(f"DELETE FROM {table} WHERE stream = %s", (stream,))
                    conn.execute(
                        "INSERT INTO streams VALUES (%s, %s, %s, NULL) ON CONFLICT (stream) DO UPDATE SET "
                        "created = excluded.created, last_seq = excluded.last_seq, snapshot_seq = NULL",
                        (stream, time.time(), seq),
                    )
                else:
                    conn.execute(
                        "INSERT INTO streams VALUES (%s, %s, %s, NULL) "
                        "ON CONFLICT (stream) DO UPDATE SET last_seq = excluded.last_seq",
                        (stream, time.time(), seq),
                    )
                conn.execute(
                    "INSERT INTO poses VALUES (%s, %s, %s, %s, %s, %s) ON CONFLICT (stream, seq) DO UPDATE SET "
                    "stamp = excluded.stamp, digest = excluded.digest, status = excluded.status, pose = excluded.pose",
                    (stream, seq, float(stamp), digest, status, pose_bytes),
                )
                conn.execute(
                    "INSERT INTO journal VALUES (%s, %s, %s) "
                    "ON CONFLICT (stream, seq) DO UPDATE SET frame = excluded.frame",
                    (stream, seq, frame_blob),
                )
                conn.execute(self._sql(COMMIT_USAGE), (time.time(), grown, new_trajectory, client, stream))
                t2 = time.perf_counter()
            phases["begin"], phases["commit"] = (t1 - t0) * 1000.0, (time.perf_counter() - t2) * 1000.0

        self.pool.run(tx, phases)
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
        """What a committed frame did after its pose (TrajectoryStore.finish_frame); committed asynchronously: the
        resume's replay of the journal redoes it if lost."""
        blobs = {k: pack_arrays(b) for k, b in (evicted or {}).items()}
        restored = list(restored)

        def tx(conn):
            with conn.transaction(), conn.cursor() as cur:
                cur.execute("SET LOCAL synchronous_commit = off")
                self._fence(cur, stream, epoch)
                if pose is not None:
                    cur.execute(
                        "UPDATE poses SET status = 'relocalised', pose = %s WHERE stream = %s AND seq = %s",
                        (np.ascontiguousarray(pose, np.float64).reshape(4, 4).tobytes(), stream, seq),
                    )
                if restored:
                    cur.executemany(
                        "UPDATE cold_tiles SET restored_seq = %s "
                        "WHERE stream = %s AND ix = %s AND iy = %s AND evicted_seq = %s",
                        [(seq, stream, ix, iy, e) for ix, iy, e in restored],
                    )
                if blobs:
                    cur.executemany(
                        "INSERT INTO cold_tiles VALUES (%s, %s, %s, %s, NULL, %s) "
                        "ON CONFLICT (stream, ix, iy, evicted_seq) DO UPDATE SET restored_seq = NULL, block = "
                        "excluded.block",
                        [(stream, ix, iy, seq, blob) for (ix, iy), blob in blobs.items()],
                    )
                    cur.execute(self._sql(GROW), (sum(map(len, blobs.values())), stream))

        self.pool.run(tx)

    def journal(self, stream: str, after_seq: int | None) -> list[tuple[int, OccupancyFrame]]:
        rows = self._read(
            "SELECT seq, frame FROM journal WHERE stream = %s AND seq > %s ORDER BY seq",
            (stream, -1 if after_seq is None else after_seq),
            True,
        )
        return [(int(s), unpack_frame(b)) for s, b in rows]

    # -- snapshots
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
        covers go (TrajectoryStore.write_snapshot). The state is streamed into the row (binary COPY) from the
        arrays' own memory, never packed whole. Two transactions, as in SQLite, so that the long first one holds no
        row a frame commit needs: it writes the snapshot unless one of a later epoch is there; the second, fenced,
        deletes what the snapshot covers if the trajectory is still the one snapshotted (False otherwise)."""
        if epoch is None and self.fenced_only:
            raise FencedError(stream, None, None)
        created = self.created(stream) if created is None else created
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

        self.pool.run(lambda conn: self._copy_snapshot(conn, stream, epoch, row_head, head, items))
        return self.pool.run(lambda conn: self._snapshot_covers(conn, stream, seq, created, epoch))

    @staticmethod
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

    def _snapshot_covers(self, conn, stream: str, seq: int, created: float, epoch: int | None) -> bool:
        """The second, fenced: the journal and restored cold rows the snapshot covers deleted, if the trajectory is
        still the one snapshotted."""
        with conn.transaction():
            conn.execute("SET LOCAL synchronous_commit = off")  # lost in a crash: the next snapshot does it
            self._fence(conn, stream, epoch)
            row = conn.execute("SELECT created FROM streams WHERE stream = %s FOR UPDATE", (stream,)).fetchone()
            if row is None or row[0] != created:
                return False
            conn.execute("DELETE FROM journal WHERE stream = %s AND seq <= %s", (stream, seq))
            conn.execute(
                "DELETE FROM cold_tiles WHERE stream = %s AND restored_seq IS NOT NULL AND restored_seq <= %s",
                (stream, seq),
            )
            conn.execute("UPDATE streams SET snapshot_seq = %s WHERE stream = %s", (seq, stream))
            return True

    def drop_old_snapshots(self, stream: str, *, epoch: int | None = None) -> int:
        """Deletes the stream's snapshot of a trajectory it no longer has; the rows deleted."""

        def tx(conn):
            with conn.transaction():
                self._fence(conn, stream, epoch)
                return conn.execute(
                    "DELETE FROM snapshots s WHERE s.stream = %s AND s.created IS DISTINCT FROM "
                    "(SELECT created FROM streams WHERE stream = %s)",
                    (stream, stream),
                ).rowcount

        return self.pool.run(tx)

    def snapshot(self, stream: str) -> tuple[int, bytes] | None:
        """(seq, state) of the stream's current trajectory, or None (TrajectoryStore.snapshot)."""

        def read(conn):
            with conn.transaction():  # one view of both rows
                conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ")
                record = conn.execute("SELECT created, last_seq FROM streams WHERE stream = %s", (stream,)).fetchone()
                snap = conn.execute(
                    "SELECT created, seq, state FROM snapshots WHERE stream = %s", (stream,), binary=True
                ).fetchone()
            return record, snap

        record, snap = self.pool.run(read)
        if snap is None or record is None or snap[0] != record[0] or record[1] is None or snap[1] > record[1]:
            return None
        return int(snap[1]), snap[2]

    # -- evicted map
    def cold_index(self, stream: str, as_of_seq: int | None = None) -> dict[tuple[int, int], list[int]]:
        if as_of_seq is None:
            rows = self._read(
                "SELECT ix, iy, evicted_seq FROM cold_tiles WHERE stream = %s AND restored_seq IS NULL", (stream,)
            )
        else:
            rows = self._read(
                "SELECT ix, iy, evicted_seq FROM cold_tiles WHERE stream = %s AND evicted_seq <= %s "
                "AND (restored_seq IS NULL OR restored_seq > %s)",
                (stream, as_of_seq, as_of_seq),
            )
        out: dict[tuple[int, int], list[int]] = {}
        for ix, iy, e in sorted(rows):
            out.setdefault((int(ix), int(iy)), []).append(int(e))
        return out

    def cold_block(self, stream: str, ix: int, iy: int, evicted_seq: int) -> bytes:
        rows = self._read(
            "SELECT block FROM cold_tiles WHERE stream = %s AND ix = %s AND iy = %s AND evicted_seq = %s",
            (stream, ix, iy, evicted_seq),
            True,
        )
        if not rows:
            raise KeyError(f"stream {stream}: no cold tile {ix},{iy} evicted at seq {evicted_seq}")
        return rows[0][0]

    # -- housekeeping
    def delete_stream(self, stream: str, *, epoch: int | None = None) -> int:
        """Everything of a stream gone (TrajectoryStore.delete_stream), fenced as a write; the poses deleted."""

        def tx(conn):
            with conn.transaction():
                self._fence(conn, stream, epoch)
                n = conn.execute("DELETE FROM poses WHERE stream = %s", (stream,)).rowcount
                for table in ("journal", "cold_tiles", "snapshots", "leases", "streams"):
                    conn.execute(f"DELETE FROM {table} WHERE stream = %s", (stream,))
                return n

        return self.pool.run(tx)

    def sizes(self, stream: str) -> dict[str, int]:
        """Rows and blob bytes per table of one stream (for stats and tests)."""
        out = {}
        for table, blob in (("poses", "pose"), ("snapshots", "state"), ("journal", "frame"), ("cold_tiles", "block")):
            sql = f"SELECT COUNT(*), COALESCE(SUM(octet_length({blob})), 0) FROM {table} WHERE stream = %s"
            n, b = self._read(sql, (stream,))[0]
            out[f"{table}_rows"], out[f"{table}_bytes"] = int(n), int(b)
        return out

    def file_sizes_mb(self) -> dict[str, float]:
        """The database's size, MB (for logs); nothing if it cannot be reached."""
        try:
            (size,) = self._read("SELECT pg_database_size(current_database())")[0]
        except StoreUnavailable:
            return {}
        return {"db_mb": round(size / 2**20, 1)}

    def close(self) -> None:
        self.pool.close()
