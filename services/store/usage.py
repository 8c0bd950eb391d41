"""What the store records for retention, in either database: each stream's client (who wrote it last), its bytes and
the time of its last frame (columns of `streams`), and the reads the registration worker's quotas and stream TTL make
(services/registration/retention.py).

`bytes` is the stream's stored size: measured (its poses, journal, snapshot with the rest of its last page, cold
tiles and, where the map service shares the store, its map tiles) after each snapshot, plus what each frame's commit
and eviction wrote since. A store written before these columns gets them when it is opened; its streams belong to no
client until they are written again, and their TTL runs from their `created`."""

from __future__ import annotations

# one statement in commit_frame's transaction: (time, bytes written, new trajectory, client, stream)
COMMIT_USAGE = (
    "UPDATE streams SET last_write = ?, bytes = ? + (CASE WHEN ? THEN 0 ELSE bytes END), "
    "client = COALESCE(?, client) WHERE stream = ?"
)
GROW = "UPDATE streams SET bytes = bytes + ? WHERE stream = ?"


def frame_bytes(digest: bytes, frame_blob: bytes) -> int:
    """What a frame's commit adds: its journal entry and its pose row (4x4 float64, stamp, digest)."""
    return len(frame_blob) + len(digest) + 136


class Usage:
    """The retention reads and the measurement on a store's database; `space` is how that database lays the rows out
    (services/store/space.py), `sizes(stream)` the stream's rows and bytes per table."""

    def __init__(self, db, space, sizes):
        self.db, self.space, self.sizes = db, space, sizes

    def usage(self, client: str) -> tuple[int, int]:
        """(streams, bytes) the store holds of a client."""
        return self.usage_of(client)[:2]

    def usage_of(self, client: str) -> tuple[int, int, int]:
        """(streams, bytes, its largest stream's bytes) the store holds of a client."""
        sql = "SELECT COUNT(*), COALESCE(SUM(bytes), 0), COALESCE(MAX(bytes), 0) FROM streams WHERE client = ?"
        n, b, biggest = self.db.read(sql, (client,))[0]
        return int(n), int(b), int(biggest)

    def stream_usage(self, stream: str) -> tuple[str | None, int, float] | None:
        """(client, bytes, last write or creation time) of a stored stream; None if it is not stored."""
        rows = self.db.read(
            "SELECT client, bytes, COALESCE(last_write, created) FROM streams WHERE stream = ?", (stream,)
        )
        return None if not rows else (rows[0][0], int(rows[0][1]), float(rows[0][2]))

    def idle_streams(self, before: float, client: str | None = None) -> list[str]:
        """Streams without a frame since `before` (time.time()), the longest idle first; of one client if given."""
        sql = "SELECT stream FROM streams WHERE COALESCE(last_write, created) < ?"
        args: tuple = (before,)
        if client is not None:
            sql, args = sql + " AND client = ?", (before, client)
        return [r[0] for r in self.db.read(sql + " ORDER BY COALESCE(last_write, created)", args)]

    def measure(self, stream: str) -> int:
        """The stream's stored bytes counted again (after a snapshot, which replaces the journal it covers)."""
        n = sum(v for k, v in self.sizes(stream).items() if k.endswith("_bytes")) + self.space.slack(stream)
        if self.space.has_map_tiles():
            n += int(
                self.db.read("SELECT COALESCE(SUM(LENGTH(data)), 0) FROM map_tiles WHERE stream = ?", (stream,))[0][0]
            )
        # lost in a power cut, the next snapshot measures it again
        self.db.write(lambda cur: cur.execute(self.db.dialect.sql(SET_BYTES), (n, stream)), synced=False)
        self.space.measure_overhead()
        return n

    def has_map_tiles(self) -> bool:
        """Whether the map service keeps its tiles in this store too (a stream's are then deleted with it)."""
        return self.space.has_map_tiles()

    def overhead(self) -> float:
        """The database's room for the rows over the bytes the streams record (at least 1), as of the store's opening
        or last measure (services/store/space.py)."""
        return self.space.overhead


SET_BYTES = "UPDATE streams SET bytes = ? WHERE stream = ?"
