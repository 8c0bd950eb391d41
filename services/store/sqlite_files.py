"""The SQLite store's files and connections: the frames' file (a writer and a reader connection) and the snapshots'
file beside it, each behind its lock, shared by the worker's stream lanes; the WAL copied into the file by a thread
of its own.

WAL journal (readers never block the writer), a busy timeout (another process may write the same file) and one
transaction per frame. synchronous=FULL by default: a pose is committed before it is published, and FULL makes that
commit survive a power cut too, not only a killed process (NORMAL does the latter; measured cost in services/README.md).

Snapshots have their own file because SQLite has one writer per file: a 100 MB snapshot written in the frames' file
held every stream's frame commit for up to a second."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from pathlib import Path

from occvo_services.os_tuning import hold_priority, release_priority
from occvo_services.store.dialect import SQLITE
from occvo_services.store.schema import SQLITE_FRAMES, SQLITE_SNAPSHOTS
from occvo_services.store.sqlite_wal import checkpoint_loop, connect, transaction


def snapshot_path(path: str | Path) -> str:
    """The snapshot file beside a store file: var/occvo.sqlite -> var/occvo.snapshots.sqlite."""
    path = str(path)
    if path == ":memory:":
        return path
    p = Path(path)
    return str(p.with_name(f"{p.stem}.snapshots{p.suffix or '.sqlite'}"))


class SqliteFiles:
    dialect = SQLITE

    def __init__(self, path: str | Path, synchronous: str, busy_timeout_s: float):
        self.path, self.snapshot_path = str(path), snapshot_path(path)
        self.synchronous, self.busy_timeout_s = synchronous, busy_timeout_s
        self.db = connect(self.path, synchronous, busy_timeout_s, SQLITE_FRAMES)
        # 64 kB pages for the snapshots' file: SQLite works per page and WAL frame, so a snapshot in 4 kB pages costs
        # several times the CPU; a file made with other pages keeps them
        self.snap_db = connect(self.snapshot_path, synchronous, busy_timeout_s, SQLITE_SNAPSHOTS, page_size=65536)
        self.lock, self.snap_lock = threading.Lock(), threading.Lock()
        self._writer_nice = os.getpriority(os.PRIO_PROCESS, 0)  # the opening thread's: write_lock holds writers at it
        # reads on a connection of their own (WAL: a reader never waits for the writer): a restore reading megabytes
        # of cold tiles held every stream's commit behind the one connection's lock
        self.read_db = self.db if self.path == ":memory:" else connect(self.path, synchronous, busy_timeout_s, "")
        self.read_lock = self.lock if self.read_db is self.db else threading.Lock()
        self.stopping, self._checkpointer = threading.Event(), None

    def start_checkpoints(self, every_s: float, wal_block_pages: int) -> None:
        """The frames' WAL is copied into the file by a thread of its own, not by the commit that crosses SQLite's
        autocheckpoint threshold: that commit held the store's lock, and every stream's commit behind it, for the
        copy and its fsync (long beside a snapshot's flush with many streams)."""
        if self.path == ":memory:":
            return
        self.checkpoint_every_s, self.wal_block_pages = every_s, wal_block_pages
        self.db.execute("PRAGMA wal_autocheckpoint=0")
        self._checkpointer = threading.Thread(
            target=checkpoint_loop, args=(self, self.busy_timeout_s), name="store-checkpointer", daemon=True
        )
        self._checkpointer.start()

    @contextlib.contextmanager
    def write_lock(self, phases: dict | None = None):
        """The frames' write lock, held at the priority of the thread that opened the store (the lanes'): a niced
        after-pose thread or snapshot writer holding it must not keep the lanes' commits waiting while other work
        takes the cores (priority ceiling; without it, on a shared host, most of a slow commit's time went to waiting
        for this lock)."""
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

    def write(self, fn, phases: dict | None = None, *, synced: bool = True, fence=None):
        """fn(db) in one write transaction of the frames' file, fence(db) first. Not `synced`: a transaction whose
        loss in a power cut costs nothing (the next synced commit, WAL commits being ordered, or the resume's replay
        redoes it): no fsync of its own, so the other streams' commits wait less."""

        def tx(db):
            if fence is not None:
                fence(db)
            return fn(db)

        with self.write_lock(phases):
            if synced:
                return transaction(self.db, tx, phases)
            self.db.execute("PRAGMA synchronous=NORMAL")
            try:
                return transaction(self.db, tx)
            finally:
                self.db.execute(f"PRAGMA synchronous={self.synchronous}")

    def read(self, sql: str, args=(), binary: bool = False) -> list:
        with self.read_lock:
            return self.read_db.execute(SQLITE.sql(sql), args).fetchall()

    def snapshots(self, fn):
        """fn(db) in one transaction of the snapshots' file."""
        with self.snap_lock:
            return transaction(self.snap_db, fn)

    def read_snapshots(self, sql: str, args=()) -> list:
        with self.snap_lock:
            return self.snap_db.execute(SQLITE.sql(sql), args).fetchall()

    def pages_in_use(self) -> int:
        """Bytes of the two files' pages in use (free pages left out: the next writes reuse them)."""
        used = 0
        for db, lock in ((self.read_db, self.read_lock), (self.snap_db, self.snap_lock)):
            with lock:
                page, count, free = (
                    db.execute(f"PRAGMA {p}").fetchone()[0] for p in ("page_size", "page_count", "freelist_count")
                )
            used += (count - free) * page
        return used

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

    def close(self) -> None:
        if self._checkpointer is not None:
            self.stopping.set()
            self._checkpointer.join()
        with self.lock, self.snap_lock:
            if self.read_db is not self.db:
                with self.read_lock:
                    self.read_db.close()
            self.db.close()
            self.snap_db.close()
