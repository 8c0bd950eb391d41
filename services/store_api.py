"""The registration worker's durable store, whichever database holds it: the interface both backends keep (an
embedded SQLite file, services/store.py; a PostgreSQL server shared by many hosts, services/store_pg.py), the
errors they raise, and the one factory that picks a backend from a URL or a path.

Leases: each stream has at most one owning worker at a time, recorded with a fencing epoch. A write given `epoch`
checks it against the stream's lease inside its own transaction and raises FencedError, writing nothing, when
another owner has taken the stream since (its epoch is higher). epoch=None writes unfenced (one embedded worker)."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from occvo_services.store_url import redact  # noqa: F401 - the one redaction, named here as before

PG_SCHEMES = ("postgresql://", "postgres://")
START_CHECK_TIMEOUT_S = 4  # libpq's connect_timeout a host address: the start check answers within 10 s


class StoreUnavailable(RuntimeError):
    """The store's database cannot be reached; the next call connects again."""


class FencedError(RuntimeError):
    """A write under an epoch the stream's lease no longer has: another worker owns the stream now."""

    def __init__(self, stream: str, epoch: int, current: int | None, owner: str | None = None):
        self.stream, self.epoch, self.current, self.owner = stream, epoch, current, owner
        now = "no lease" if current is None else f"epoch {current}" + (f" (owner {owner})" if owner else "")
        super().__init__(f"stream {stream}: write under lease epoch {epoch} refused, the lease is at {now}")


@dataclass(frozen=True)
class Lease:
    stream: str
    owner: str | None  # None: released
    epoch: int
    remaining_s: float  # until it expires (<= 0: expired), by the database's clock


def is_postgres_url(url_or_path: str | Path | None) -> bool:
    return isinstance(url_or_path, str) and url_or_path.startswith(PG_SCHEMES)


def sqlite_path(url_or_path: str | Path) -> str:
    """The file of a path or of a sqlite:/// URL (SQLAlchemy's form: sqlite:///relative, sqlite:////absolute)."""
    s = str(url_or_path)
    return s[len("sqlite:///") :] if s.startswith("sqlite:///") else s


@runtime_checkable
class Store(Protocol):
    """What the registration worker calls. Every write taking `epoch` is fenced by the stream's lease (see above)."""

    # streams and poses
    def streams(self) -> list[str]: ...
    def record(self, stream: str): ...  # StreamRecord | None
    def created(self, stream: str) -> float | None: ...
    def pose(self, stream: str, seq: int): ...  # StoredPose | None
    def poses(self, stream: str) -> list: ...  # [StoredPose]
    def journal(self, stream: str, after_seq: int | None) -> list: ...  # [(seq, OccupancyFrame)]

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
        """The frame's pose and journal entry, durable when it returns; where the time went, ms. `client`: the
        stream's client now (retention), its bytes and last write updated in the same transaction."""
        ...

    def finish_frame(
        self,
        stream: str,
        seq: int,
        pose: np.ndarray | None = None,
        evicted: dict | None = None,
        restored: Iterable[tuple[int, int, int]] = (),
        *,
        epoch: int | None = None,
    ) -> None: ...

    # snapshots
    def write_snapshot(self, stream: str, seq: int, state, created: float | None = None, *, epoch=None) -> bool: ...
    def drop_old_snapshots(self, stream: str, *, epoch: int | None = None) -> int: ...
    def snapshot(self, stream: str) -> tuple[int, bytes] | None: ...

    # evicted map
    def cold_index(self, stream: str, as_of_seq: int | None = None) -> dict[tuple[int, int], list[int]]: ...
    def cold_block(self, stream: str, ix: int, iy: int, evicted_seq: int) -> bytes: ...

    # leases
    def acquire(self, stream: str, owner: str, ttl_s: float, take_from: str | None = None) -> int | None: ...
    def renew(self, owner: str, ttl_s: float) -> list[str]: ...
    def release(self, stream: str, owner: str) -> bool: ...
    def owner_of(self, stream: str) -> str | None: ...
    def leases(self) -> list[Lease]: ...

    # retention (services/store_retention.py)
    def usage(self, client: str) -> tuple[int, int]: ...  # (streams, bytes) of a client
    def usage_of(self, client: str) -> tuple[int, int, int]: ...  # and its biggest stream's bytes
    def overhead(self) -> float: ...  # the store's pages in use over the streams' bytes (SQLite; PostgreSQL 1)
    def stream_usage(self, stream: str) -> tuple[str | None, int, float] | None: ...  # (client, bytes, last write)
    def idle_streams(self, before: float, client: str | None = None) -> list[str]: ...
    def measure(self, stream: str) -> int: ...

    # housekeeping
    def sizes(self, stream: str) -> dict[str, int]: ...
    def delete_stream(self, stream: str) -> int: ...
    def file_sizes_mb(self) -> dict[str, float]: ...
    def close(self) -> None: ...


def open_store(url_or_path: str | Path, synchronous: str = "FULL", busy_timeout_s: float = 30.0) -> Store:
    """postgresql://user@host/db: the PostgreSQL store (services/store_pg.py); a path or sqlite:///path: SQLite."""
    if is_postgres_url(url_or_path):
        from occvo_services.store_pg import PgTrajectoryStore

        return PgTrajectoryStore(str(url_or_path), synchronous)
    from occvo_services.store import TrajectoryStore

    return TrajectoryStore(sqlite_path(url_or_path), synchronous, busy_timeout_s)


def check_reachable(url_or_path: str | Path | None) -> None:
    """Once, before any worker starts: a PostgreSQL store that cannot be reached (server down, wrong host, wrong
    password, no such database) raises StoreUnavailable, one line naming the store without its password and the
    reason, instead of workers crash-looping on it. A SQLite file is embedded: nothing to reach."""
    if not is_postgres_url(url_or_path):
        return
    from occvo_services.pg_pool import _first_line, _psycopg

    pg = _psycopg()
    try:
        with pg.connect(str(url_or_path), connect_timeout=START_CHECK_TIMEOUT_S) as conn:
            conn.execute("SELECT 1")
    except pg.Error as exc:
        raise StoreUnavailable(f"store {redact(str(url_or_path))} unreachable: {_first_line(exc)}") from None
