"""The one door to a store: open_store and open_map_store pick the database from a URL or a path (a path or
sqlite:///path: SQLite; postgresql://user@host/db: PostgreSQL), and check_store is the check `occvo serve` and
`occvo up` make before any worker starts. The registration worker opens its store here and calls it through
services/store/protocols.py; nothing outside this package names a database's store."""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

from occvo_core.errors import ConfigError
from occvo_services.store.errors import StoreUnavailable
from occvo_services.store.url import is_postgres_url, redact, sqlite_path

START_CHECK_TIMEOUT_S = 4  # libpq's connect_timeout a host address: the start check answers within 10 s


def open_store(
    url_or_path: str | Path, synchronous: str = "FULL", busy_timeout_s: float = 30.0, fenced_only: bool = False
):
    """The trajectory store (services/store/protocols.TRAJECTORY_STORE names what it answers); fenced_only (placement
    "members"): every write of a stream under its lease, one without an epoch refused."""
    if is_postgres_url(url_or_path):
        from occvo_services.store.postgres import PgTrajectoryStore

        return PgTrajectoryStore(str(url_or_path), synchronous, fenced_only=fenced_only)
    from occvo_services.store.sqlite import TrajectoryStore

    return TrajectoryStore(sqlite_path(url_or_path), synchronous, busy_timeout_s, fenced_only)


def open_map_store(path: str | Path | None):
    """The map service's tiles (protocols.MapTiles): in PostgreSQL for a postgresql:// URL, in a SQLite file for a
    path or sqlite:/// URL, in memory without one; ConfigError naming the file when it cannot be opened."""
    from occvo_services.store.map_tiles import MapStore, MemoryMapStore

    if not path:
        return MemoryMapStore()
    if is_postgres_url(path):
        from occvo_services.store.map_tiles_pg import PgMapStore

        return PgMapStore(str(path))
    path = sqlite_path(path)
    try:
        return MapStore(path)
    except (sqlite3.Error, OSError) as exc:
        raise ConfigError(f"map store {path}: {type(exc).__name__}: {exc}") from None


def check_store(url: str | None, flag: str = "--store") -> None:
    """Once, before any worker starts (`occvo serve`, `occvo up`): ConfigError, one line naming the store without
    its password and what is wrong, instead of workers crash-looping on it. A SQLite file's folder must exist and be
    writable; a PostgreSQL server must answer (down, wrong host, wrong password, no such database)."""
    if url is None:
        return
    if not is_postgres_url(url):
        if "://" not in url or url.startswith("sqlite:"):
            _check_writable(url, flag)
        return
    try:
        check_reachable(url)
    except StoreUnavailable as exc:
        raise ConfigError(
            f"{exc} (checked before any worker starts: start the database or fix the store URL)"
        ) from None


def _check_writable(url: str, flag: str) -> None:
    path = Path(sqlite_path(url))
    folder = path.parent if not path.is_dir() else path
    if not folder.is_dir():
        raise ConfigError(f"{flag} {url}: folder {folder} does not exist")
    if not os.access(folder, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise ConfigError(f"{flag} {url}: {path if path.exists() else folder} is not writable")


def check_reachable(url_or_path: str | Path | None) -> None:
    """A PostgreSQL store that cannot be reached raises StoreUnavailable, one line naming the store without its
    password and the reason. A SQLite file is embedded: nothing to reach."""
    if not is_postgres_url(url_or_path):
        return
    from occvo_services.store.pg_pool import _first_line, _psycopg

    pg = _psycopg()
    try:
        with pg.connect(str(url_or_path), connect_timeout=START_CHECK_TIMEOUT_S) as conn:
            conn.execute("SELECT 1")
    except pg.Error as exc:
        raise StoreUnavailable(f"store {redact(str(url_or_path))} unreachable: {_first_line(exc)}") from None
