"""What the store answers, by concern: the registration worker types against these, never against a database
(tests/service/test_store_edges.py checks its imports). Both stores (SQLite, services/store/sqlite.py; PostgreSQL,
services/store/postgres.py) answer every one, each concern by a part of its own; the map service's stores answer
MapTiles. Every write taking `epoch` is fenced by the stream's lease (services/store/leases.py): FencedError, nothing
written, if another worker owns the stream now. StoreUnavailable while the database cannot be reached."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Protocol, runtime_checkable

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_services.store.records import Lease, StoredPose, StreamRecord


@runtime_checkable
class FrameLog(Protocol):
    """Each stream's record, its published poses and the journal of frames since its snapshot."""

    def streams(self) -> list[str]: ...
    def record(self, stream: str) -> StreamRecord | None: ...
    def created(self, stream: str) -> float | None: ...
    def pose(self, stream: str, seq: int) -> StoredPose | None: ...
    def poses(self, stream: str) -> list[StoredPose]: ...
    def journal(self, stream: str, after_seq: int | None) -> list[tuple[int, OccupancyFrame]]: ...

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
        """The frame's pose and journal entry, durable when it returns; where the time went, ms."""
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


@runtime_checkable
class Snapshots(Protocol):
    """The latest OccVO state of each stream (services/store/snapshots.py)."""

    def write_snapshot(
        self, stream: str, seq: int, state, created: float | None = None, *, epoch: int | None = None
    ) -> bool: ...
    def drop_old_snapshots(self, stream: str, *, epoch: int | None = None) -> int: ...
    def snapshot(self, stream: str) -> tuple[int, bytes] | None: ...


@runtime_checkable
class ColdTiles(Protocol):
    """The map tiles a stream's working set evicted."""

    def cold_index(self, stream: str, as_of_seq: int | None = None) -> dict[tuple[int, int], list[int]]: ...
    def cold_block(self, stream: str, ix: int, iy: int, evicted_seq: int) -> bytes: ...


@runtime_checkable
class Leases(Protocol):
    """Which worker owns each stream, under a fencing epoch (and `fenced_only`: every write needs one)."""

    def acquire(self, stream: str, owner: str, ttl_s: float, take_from: str | None = None) -> int | None: ...
    def renew(self, owner: str, ttl_s: float) -> list[str]: ...
    def drop_unused_leases(self, owner: str, keep: list[str]) -> int: ...
    def release(self, stream: str, owner: str) -> bool: ...
    def owner_of(self, stream: str) -> str | None: ...
    def leases(self) -> list[Lease]: ...


@runtime_checkable
class Usage(Protocol):
    """What each client's streams take (retention: quotas and the stream TTL)."""

    def usage(self, client: str) -> tuple[int, int]: ...  # (streams, bytes) of a client
    def usage_of(self, client: str) -> tuple[int, int, int]: ...  # and its biggest stream's bytes
    def stream_usage(self, stream: str) -> tuple[str | None, int, float] | None: ...  # (client, bytes, last write)
    def idle_streams(self, before: float, client: str | None = None) -> list[str]: ...
    def measure(self, stream: str) -> int: ...
    def overhead(self) -> float: ...  # the database's room for the rows over their bytes (>= 1)
    def has_map_tiles(self) -> bool: ...  # the map service's tiles share this store (deleted with their stream)


@runtime_checkable
class Housekeeping(Protocol):
    """The store as a whole."""

    def ping(self) -> None: ...
    def sizes(self, stream: str) -> dict[str, int]: ...  # rows and blob bytes per table of one stream
    def delete_stream(self, stream: str, *, epoch: int | None = None) -> int: ...
    def file_sizes_mb(self) -> dict[str, float]: ...
    def close(self) -> None: ...


@runtime_checkable
class MapTiles(Protocol):
    """The map service's encoded tiles of each stream."""

    def apply(self, update, encoded: list[bytes]) -> None: ...
    def streams(self) -> list[str]: ...
    def tiles(self, stream: str, ix=None, iy=None, bounds=None, limit: int | None = None) -> list: ...
    def info(self, stream: str): ...
    def delete_stream(self, stream: str) -> int: ...
    def close(self) -> None: ...


TRAJECTORY_STORE = (FrameLog, Snapshots, ColdTiles, Leases, Usage, Housekeeping)  # what open_store's stores answer


def calls(protocol: type) -> list[str]:
    """The calls a protocol names."""
    return [name for name, value in vars(protocol).items() if callable(value) and not name.startswith("_")]


def answer(store, part, protocol: type) -> None:
    """`store` answers `protocol`'s calls with `part`'s: a store is built from parts, one a concern."""
    for name in calls(protocol):
        setattr(store, name, getattr(part, name))
