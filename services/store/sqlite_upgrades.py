"""A SQLite store written by an earlier version, brought up to date when it is opened: snapshots moved to their own
file, their lease epochs, the retention columns. Each is safe against another process opening the same store."""

from __future__ import annotations

import sqlite3

RETENTION_COLUMNS = (("client", "TEXT"), ("bytes", "INTEGER NOT NULL DEFAULT 0"), ("last_write", "REAL"))


def upgrade(files) -> None:
    move_old_snapshots(files)
    add_snapshot_epochs(files)
    add_retention_columns(files)


def move_old_snapshots(files) -> None:
    """A store written before snapshots had their own file: move its snapshots there (its journal needs them).
    In one transaction of the frames' file, so two workers opening the store at once move them once."""

    def old_table(db) -> bool:
        return db.execute("SELECT 1 FROM sqlite_master WHERE type='table' AND name='snapshots'").fetchone() is not None

    def tx(db):
        if not old_table(db):  # the other worker moved them
            return
        rows = db.execute(
            "SELECT s.stream, t.created, s.seq, s.state FROM snapshots s JOIN streams t USING (stream)"
        ).fetchall()
        files.snapshots(
            lambda snap: snap.executemany(
                "INSERT OR REPLACE INTO snapshots (stream, created, seq, state) VALUES (?, ?, ?, ?)", rows
            )
        )
        db.execute("DROP TABLE snapshots")

    if files.read("SELECT 1 FROM sqlite_master WHERE type='table' AND name='snapshots'"):  # else no write lock
        files.write(tx)


def add_snapshot_epochs(files) -> None:
    """A snapshots' file from before leases: its table gets the epoch column (NULL: written unfenced)."""
    files.snapshots(lambda db: _add_column(db, "snapshots", "epoch", "INTEGER"))


def add_retention_columns(files) -> None:
    def tx(db):
        for name, kind in RETENTION_COLUMNS:
            _add_column(db, "streams", name, kind)
        db.execute("CREATE INDEX IF NOT EXISTS streams_client ON streams (client)")

    files.write(tx)


def _add_column(db, table: str, name: str, kind: str) -> None:
    if name in {r[1] for r in db.execute(f"PRAGMA table_info({table})")}:
        return
    try:
        db.execute(f"ALTER TABLE {table} ADD COLUMN {name} {kind}")
    except sqlite3.OperationalError as exc:  # another process added it meanwhile
        if "duplicate column" not in str(exc):
            raise
