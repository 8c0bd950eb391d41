"""The store in a PostgreSQL database that workers on many hosts share, by URL: what the SQLite store keeps in files
(streams, poses, journal, cold tiles, snapshots, leases) in one database, built from the same parts (services/store/
protocols.py names each concern) on pooled connections (services/store/pg_database.py). Snapshots are copied in
binary (services/store/pg_snapshots.py); lease expiry uses the server's clock, so the hosts' clocks do not matter."""

from __future__ import annotations

from occvo_services.store import protocols
from occvo_services.store.cold_tiles import ColdTiles
from occvo_services.store.frame_log import FrameLog
from occvo_services.store.leases import LeaseTable
from occvo_services.store.pg_database import PgDatabase
from occvo_services.store.pg_snapshots import PgSnapshots
from occvo_services.store.records import SIZES
from occvo_services.store.space import PgRows
from occvo_services.store.usage import Usage


class PgTrajectoryStore:
    def __init__(self, url: str, synchronous: str = "FULL", pool_size: int = 4, fenced_only: bool = False):
        self.database = db = PgDatabase(url, synchronous, pool_size)
        self.path, self.synchronous, self.pool, self.label = url, synchronous, db.pool, db.label
        self.lease_table = LeaseTable(db, fenced_only)
        self.frame_log = FrameLog(db, self.lease_table)
        self.snapshot_rows = PgSnapshots(db, self.frame_log, self.lease_table)
        for part, protocol in (
            (self.frame_log, protocols.FrameLog),
            (self.snapshot_rows, protocols.Snapshots),
            (ColdTiles(db), protocols.ColdTiles),
            (self.lease_table, protocols.Leases),
            (Usage(db, PgRows(db), self.sizes), protocols.Usage),
        ):
            protocols.answer(self, part, protocol)

    @property
    def fenced_only(self) -> bool:
        return self.lease_table.fenced_only

    def ping(self) -> None:
        self.database.read("SELECT 1")  # StoreUnavailable while the server is away

    def sizes(self, stream: str) -> dict[str, int]:
        """Rows and blob bytes per table of one stream (for stats and tests)."""
        got = {**self.frame_log.sizes(stream), **self.snapshot_rows.sizes(stream)}
        return {f"{t}_{k}": got[f"{t}_{k}"] for t in SIZES for k in ("rows", "bytes")}

    def delete_stream(self, stream: str, *, epoch: int | None = None) -> int:
        """Everything of a stream gone, in one transaction, fenced as a write; the poses deleted."""
        return self.frame_log.delete_stream(stream, epoch=epoch, also=("snapshots",))

    def file_sizes_mb(self) -> dict[str, float]:
        return self.database.file_sizes_mb()

    def close(self) -> None:
        self.database.close()
