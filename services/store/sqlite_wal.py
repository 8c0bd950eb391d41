"""SQLite files that several processes open at once (registration shards and the map service share one store): WAL
mode, connections, write transactions and the WAL's checkpoints."""

from __future__ import annotations

import logging
import random
import sqlite3
import time
from pathlib import Path

from occvo_core.errors import ConfigError

_LOG = logging.getLogger("occvo.registration.store")  # the worker's logger prints it


def enable_wal(db: sqlite3.Connection, busy_timeout_s: float) -> None:
    """PRAGMA journal_mode=WAL, retried while another process holds the file: on a new file the switch needs it
    exclusively and SQLite answers "database is locked" at once instead of calling the busy handler, so shards
    started together failed 13 trials of 30 (four processes opening one new store)."""
    deadline = time.monotonic() + busy_timeout_s
    delay = 0.005
    while True:
        try:
            mode = db.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            break
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() >= deadline:
                raise
            time.sleep(delay * (1.0 + random.random()))  # jittered: the openers do not retry in step
            delay = min(2.0 * delay, 0.1)
    if str(mode).lower() != "wal":
        raise sqlite3.OperationalError(f"cannot use WAL journal mode (got {mode})")


def connect(
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


def transaction(db: sqlite3.Connection, fn, phases: dict | None = None):
    """fn(db) in one write transaction. phases, if given, gets the ms spent waiting for the file's write lock
    ("begin": another connection or process writing) and committing ("commit": the WAL write and its sync)."""
    t0 = time.perf_counter()
    db.execute("BEGIN IMMEDIATE")
    t1 = time.perf_counter()
    try:
        out = fn(db)
    except BaseException:
        if db.in_transaction:  # SQLite rolls back itself on some errors (SQLITE_FULL): the first error is the one
            db.execute("ROLLBACK")
        raise
    t2 = time.perf_counter()
    try:
        db.execute("COMMIT")
    except BaseException:
        if db.in_transaction:
            db.execute("ROLLBACK")
        raise
    if phases is not None:
        phases["begin"], phases["commit"] = (t1 - t0) * 1000.0, (time.perf_counter() - t2) * 1000.0
    return out


def checkpoint_loop(files, busy_timeout_s: float) -> None:
    """A store's checkpoint thread: PASSIVE checkpoints (they copy what no reader needs and never wait for a writer)
    every files.checkpoint_every_s, on their own connection; a WAL of files.wal_block_pages after a pass is
    checkpointed whole (writers waiting); the next commit after a complete one starts the WAL over. Until
    files.stopping is set."""
    from occvo_services.os_tuning import lower_priority, name_os_thread
    from occvo_services.telemetry import log_event

    db = connect(files.path, files.synchronous, busy_timeout_s, "")
    name_os_thread("store-checkpoint")
    lower_priority(10)  # below the threads that commit poses (best effort)
    failing = False
    try:
        while not files.stopping.wait(files.checkpoint_every_s):
            try:
                _, log_pages, _ = db.execute("PRAGMA wal_checkpoint(PASSIVE)").fetchone()
                if log_pages >= files.wal_block_pages:
                    db.execute("PRAGMA wal_checkpoint(RESTART)")
                failing = False
            except sqlite3.Error as exc:  # busy or an I/O error: the next pass tries again; said once a run of them
                if not failing:
                    message = "WAL checkpoint failed; retrying every pass (the WAL grows meanwhile)"
                    log_event(_LOG, message, logging.WARNING, path=files.path, error=repr(exc))
                failing = True
    finally:
        db.close()
