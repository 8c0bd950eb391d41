"""WAL mode for a SQLite file that several processes open at once (registration shards and the map service share
one store)."""

from __future__ import annotations

import random
import sqlite3
import time


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
