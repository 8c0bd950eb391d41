"""The map service's tiles in PostgreSQL (tables map_streams, map_tiles beside the registration worker's,
services/store/postgres.py): MapStore's methods (services/store/map_tiles.py), so map-service replicas on many hosts serve one
map. Each MapUpdate is one transaction, committed asynchronously as SQLite's synchronous=NORMAL: a tile lost in a
server crash comes again with the stream's next update of it."""

from __future__ import annotations

from occvo_schemas.models import MapInfo, MapUpdate
from occvo_services.store import map_tiles_sql as sql
from occvo_services.store.dialect import POSTGRES
from occvo_services.store.map_tiles import Bounds, _info, _tile_rows
from occvo_services.store.pg_pool import PgPool

SCHEMA = """
CREATE TABLE IF NOT EXISTS map_streams (
    stream   TEXT PRIMARY KEY,
    tile_m   DOUBLE PRECISION NOT NULL,
    last_seq BIGINT
);
CREATE TABLE IF NOT EXISTS map_tiles (
    stream TEXT NOT NULL,
    ix     INTEGER NOT NULL,
    iy     INTEGER NOT NULL,
    voxels INTEGER NOT NULL,
    -- x_min, not SQLite's xmin: PostgreSQL's system columns take xmin and xmax
    x_min DOUBLE PRECISION NOT NULL, y_min DOUBLE PRECISION NOT NULL, z_min DOUBLE PRECISION NOT NULL,
    x_max DOUBLE PRECISION NOT NULL, y_max DOUBLE PRECISION NOT NULL, z_max DOUBLE PRECISION NOT NULL,
    data   BYTEA NOT NULL,
    PRIMARY KEY (stream, ix, iy)
);
ALTER TABLE map_tiles ALTER COLUMN data SET STORAGE EXTERNAL;
"""


class PgMapStore:
    def __init__(self, url: str, pool_size: int = 3):
        self.path = url
        self.pool = PgPool(url, pool_size, "map store", SCHEMA)

    def apply(self, update: MapUpdate, encoded: list[bytes]) -> None:
        """One transaction: a reset deletes the stream's tiles first; an empty tile deletes that tile."""
        tx = sql.apply(POSTGRES.sql, sql.POSTGRES_BOUNDS, update, list(_tile_rows(update, encoded)))

        def run(conn):
            with conn.transaction(), conn.cursor() as cur:
                cur.execute("SET LOCAL synchronous_commit = off")
                tx(cur)

        self.pool.run(run)

    def delete_stream(self, stream: str) -> int:
        """The stream's map gone (`occvo store delete`); the tiles deleted."""

        def run(conn):
            with conn.transaction(), conn.cursor() as cur:
                return sql.delete_stream(POSTGRES.sql, stream)(cur)

        return self.pool.run(run)

    def streams(self) -> list[str]:
        return self.pool.run(
            lambda conn: [r[0] for r in conn.execute("SELECT stream FROM map_streams ORDER BY stream")]
        )

    def tiles(
        self, stream: str, ix: int | None = None, iy: int | None = None, bounds: Bounds = None, limit: int | None = None
    ) -> list[tuple[int, int, bytes]]:
        """Encoded tiles of a stream: the one at (ix, iy) when both are given, else the first `limit` within bounds."""
        query, args = sql.tiles(stream, ix, iy, bounds, limit)
        rows = self.pool.run(lambda conn: conn.execute(POSTGRES.sql(query), args, binary=True).fetchall())
        return [(int(x), int(y), bytes(d)) for x, y, d in rows]

    def info(self, stream: str) -> MapInfo | None:
        def read(conn):
            with conn.transaction(), conn.cursor() as cur:  # one view for the three reads
                cur.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ")
                return sql.info(POSTGRES.sql, sql.POSTGRES_BOUNDS, stream)(cur)

        got = self.pool.run(read)
        if got is None:
            return None
        row, agg, tiles = got
        lo, hi = (agg[1:4], agg[4:7]) if tiles else (None, None)
        return _info(stream, row[0], row[1], [tuple(t) for t in tiles], int(agg[0]), lo, hi)

    def close(self) -> None:
        self.pool.close()
