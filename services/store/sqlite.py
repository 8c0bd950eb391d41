"""The store in embedded SQLite files, one row set per stream, for the workers of one host: built from the parts
both databases share (the frame log, cold tiles, leases, usage; services/store/protocols.py names each concern) on
SQLite's files (services/store/sqlite_files.py), with the snapshots in a file of their own. The tables may share the
frames' file with the map service's (services/store/map_tiles.py)."""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from occvo_services.store import protocols
from occvo_services.store.cold_tiles import ColdTiles
from occvo_services.store.frame_log import FrameLog
from occvo_services.store.leases import LeaseTable
from occvo_services.store.records import SIZES
from occvo_services.store.space import SqlitePages
from occvo_services.store.sqlite_files import SqliteFiles
from occvo_services.store.sqlite_snapshots import SqliteSnapshots
from occvo_services.store.sqlite_upgrades import upgrade
from occvo_services.store.usage import Usage


class TrajectoryStore:
    CHECKPOINT_EVERY_S = 1.0
    WAL_BLOCK_PAGES = 65536  # a WAL this long (256 MB of 4 kB pages) after a pass: checkpoint it whole, writers waiting

    def __init__(
        self,
        path: str | Path,
        synchronous: Literal["NORMAL", "FULL"] = "FULL",
        busy_timeout_s: float = 30.0,
        fenced_only: bool = False,
    ):
        self.files = files = SqliteFiles(path, synchronous, busy_timeout_s)
        self.path, self.snapshot_path, self.synchronous = files.path, files.snapshot_path, synchronous
        # the connections and the frames' write lock, as tools and tests reach them
        self.db, self.snap_db, self.lock = files.db, files.snap_db, files.lock
        self._write, self._read = files.write, files.read
        upgrade(files)
        self.lease_table = LeaseTable(files, fenced_only)
        self.frame_log = FrameLog(files, self.lease_table)
        self.snapshot_file = SqliteSnapshots(files, self.frame_log, self.lease_table)
        self.retention = Usage(files, SqlitePages(files), self.sizes)
        for part, protocol in (
            (self.frame_log, protocols.FrameLog),
            (self.snapshot_file, protocols.Snapshots),
            (ColdTiles(files), protocols.ColdTiles),
            (self.lease_table, protocols.Leases),
            (self.retention, protocols.Usage),
        ):
            protocols.answer(self, part, protocol)
        self.retention.space.measure_overhead()
        files.start_checkpoints(self.CHECKPOINT_EVERY_S, self.WAL_BLOCK_PAGES)

    @property
    def fenced_only(self) -> bool:
        return self.lease_table.fenced_only

    def ping(self) -> None:
        self.files.read("SELECT 1")

    def sizes(self, stream: str) -> dict[str, int]:
        """Rows and blob bytes per table of one stream (for stats and tests)."""
        got = {**self.frame_log.sizes(stream), **self.snapshot_file.sizes(stream)}
        return {f"{t}_{k}": got[f"{t}_{k}"] for t in SIZES for k in ("rows", "bytes")}

    def delete_stream(self, stream: str, *, epoch: int | None = None) -> int:
        """Everything of a stream gone: trajectory, journal, cold tiles, lease, snapshot (`occvo store delete`; a
        worker's, fenced); the poses deleted. Its workers must not serve it meanwhile (their state would write it back)."""
        n = self.frame_log.delete_stream(stream, epoch=epoch)
        self.snapshot_file.delete(stream)
        return n

    def file_sizes_mb(self) -> dict[str, float]:
        return self.files.file_sizes_mb()

    def close(self) -> None:
        self.files.close()
