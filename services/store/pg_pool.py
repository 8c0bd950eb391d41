"""Connections to a PostgreSQL store shared by the threads of one process (services/store/pg_database.py,
services/store/map_tiles_pg.py): a few connections handed out one per call, so that a snapshot being written or a restore
reading cold tiles never holds another stream's frame commit.

A database that cannot be reached raises StoreUnavailable naming the store (its URL without the password), not the
driver's error. A broken connection is dropped; the next call connects again, so the store works once the server is
back. A call that finds its pooled connection broken (the server restarted since) runs once more on a fresh one:
every transaction of the stores is idempotent (upserts of the same rows), so running one twice is harmless."""

from __future__ import annotations

import threading
import time
from contextlib import contextmanager

from occvo_services.store.errors import StoreUnavailable
from occvo_services.store.url import redact

CONNECT_TIMEOUT_S = 5
# a host gone without a FIN (partition, power) is noticed in seconds, not after the kernel's two hours
KEEPALIVE = {
    "keepalives": 1,
    "keepalives_idle": 5,
    "keepalives_interval": 2,
    "keepalives_count": 3,
    "tcp_user_timeout": 10_000,  # ms: data unacknowledged this long (a call in flight) breaks the connection
}
# a process stopped inside a transaction (SIGSTOP, a paused VM) would hold its lease row, and so a takeover of its
# streams, for as long as it stays stopped: the server ends such a session after this long
IDLE_IN_TRANSACTION_S = 5


def _psycopg():
    try:
        import psycopg
    except ImportError:
        raise StoreUnavailable(
            "a postgresql:// store needs psycopg 3: pip install 'occvo[postgres]' (or 'psycopg[binary]')"
        ) from None
    return psycopg


class PgPool:
    def __init__(self, url: str, size: int = 4, what: str = "store", setup: str = ""):
        self.url, self.label, self.setup = url, f"{what} {redact(url)}", setup
        self.pg = _psycopg()
        self._idle: list = []
        self._slots = threading.BoundedSemaphore(size)
        self._lock = threading.Lock()
        self._closed = False
        self.run(lambda conn: None)  # reachable now, or StoreUnavailable at once (and the schema made)

    def _connect(self):
        try:
            conn = self.pg.connect(
                self.url,
                autocommit=True,
                connect_timeout=CONNECT_TIMEOUT_S,
                options=f"-c idle_in_transaction_session_timeout={IDLE_IN_TRANSACTION_S * 1000}",
                **KEEPALIVE,
            )
        except self.pg.OperationalError as exc:
            raise StoreUnavailable(f"{self.label} unreachable: {_first_line(exc)}") from None
        if self.setup:
            self._schema(conn)
        return conn

    def _schema(self, conn) -> None:
        # under an advisory lock: CREATE TABLE IF NOT EXISTS from processes starting together can collide
        with conn.transaction():
            conn.execute("SELECT pg_advisory_xact_lock(7260000054)")
            conn.execute(self.setup)
        self.setup = ""  # once a process

    @contextmanager
    def connection(self, wait_ms: dict | None = None):
        """(connection, reused) of the pool for one call; StoreUnavailable if the server cannot be reached."""
        t0 = time.perf_counter()
        self._slots.acquire()
        if wait_ms is not None:
            wait_ms["lock"] = (time.perf_counter() - t0) * 1000.0
        conn = None
        try:
            with self._lock:
                if self._closed:
                    raise StoreUnavailable(f"{self.label} is closed")
                conn = self._idle.pop() if self._idle else None
            reused = conn is not None and not conn.closed
            if not reused:
                conn = self._connect()
            yield conn, reused
        finally:
            if conn is not None:
                with self._lock:
                    if not conn.closed and not conn.broken and not self._closed:
                        self._idle.append(conn)
                    else:
                        conn.close()
            self._slots.release()

    def run(self, fn, wait_ms: dict | None = None):
        """fn(conn) on a pooled connection (autocommit: fn opens its transactions); once more on a fresh connection
        if the pooled one turned out broken; StoreUnavailable if the server is down."""
        for attempt in (0, 1):
            with self.connection(wait_ms) as (conn, reused):
                reused = reused and attempt == 0
                try:
                    return fn(conn)
                except self.pg.Error as exc:
                    if not conn.broken and not conn.closed:
                        raise  # the server answered (disk full, a timeout): its error, as it is
                    # the connection is gone (server down or restarted, the session ended by the server, a peer
                    # silent past the keepalives)
                    conn.close()
                    if not reused:
                        raise StoreUnavailable(f"{self.label} unreachable: {_first_line(exc)}") from None
        raise AssertionError("unreachable")

    def close(self) -> None:
        with self._lock:
            self._closed = True
            idle, self._idle = self._idle, []
        for conn in idle:
            conn.close()


def _first_line(exc: Exception) -> str:
    text = redact(str(exc)).strip()  # libpq may quote the conninfo it could not parse; redacted before it is cut
    return (text.splitlines()[0] if text else type(exc).__name__)[:300]
