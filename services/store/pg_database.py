"""The PostgreSQL store's database: its pooled connections (services/store/pg_pool.py) as the parts use them, reads
and write transactions, as services/store/sqlite_files.py gives them for SQLite.

Durability as in SQLite: a synced write that returned is durable (synchronous_commit on; the server runs with
fsync); the writes whose loss the resume redoes commit asynchronously, and the next synchronous commit carries them
(the WAL is flushed in order)."""

from __future__ import annotations

import time

from occvo_services.store.dialect import POSTGRES
from occvo_services.store.errors import StoreUnavailable
from occvo_services.store.pg_pool import PgPool
from occvo_services.store.schema import POSTGRES as SCHEMA


class PgDatabase:
    dialect = POSTGRES

    def __init__(self, url: str, synchronous: str = "FULL", pool_size: int = 4):
        self.path = url  # what the worker logs: the pool redacts it where it names the store
        self.pool = PgPool(url, pool_size, "trajectory store", SCHEMA)
        self.label = self.pool.label
        # NORMAL (store_sync "normal"): frame commits asynchronous too, a server crash may lose the last ones
        self._synced = synchronous.upper() == "FULL"

    def write(self, fn, phases: dict | None = None, *, synced: bool = True, fence=None):
        """fn(cursor) in one transaction, fence(cursor) first. Where the time went, ms, in `phases`: "lock"
        (waiting for a connection), "begin" (the lease, or a takeover holding it), "commit"."""

        def tx(conn):
            t0 = time.perf_counter()
            with conn.transaction(), conn.cursor() as cur:
                if not (synced and self._synced):
                    cur.execute("SET LOCAL synchronous_commit = off")
                if fence is not None:
                    fence(cur)
                t1 = time.perf_counter()
                out = fn(cur)
                t2 = time.perf_counter()
            if phases is not None:
                phases["begin"], phases["commit"] = (t1 - t0) * 1000.0, (time.perf_counter() - t2) * 1000.0
            return out

        return self.pool.run(tx, phases)

    def read(self, sql: str, args=(), binary: bool = False) -> list:
        return self.pool.run(lambda conn: conn.execute(POSTGRES.sql(sql), args, binary=binary).fetchall())

    def file_sizes_mb(self) -> dict[str, float]:
        """The database's size, MB (for logs); nothing if it cannot be reached."""
        try:
            (size,) = self.read("SELECT pg_database_size(current_database())")[0]
        except StoreUnavailable:
            return {}
        return {"db_mb": round(size / 2**20, 1)}

    def close(self) -> None:
        self.pool.close()
