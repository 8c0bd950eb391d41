"""The map service's tiles in PostgreSQL (tables map_streams, map_tiles beside the registration worker's,
services/store/postgres.py): MapStore's methods (services/store/map_tiles.py), so map-service replicas on many hosts serve one
map. Each MapUpdate is one transaction, committed asynchronously as SQLite's synchronous=NORMAL: a tile lost in a
server crash comes again with the stream's next update of it."""

from __future__ import annotations

from occvo_schemas.models import MapInfo, MapUpdate
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
        rows = list(_tile_rows(update, encoded))
        gone = [(update.stream, ix, iy) for ix, iy, n, *_ in rows if n == 0]
        kept = [(update.stream, ix, iy, n, *lo, *hi, data) for ix, iy, n, lo, hi, data in rows if n]

        def tx(conn):
            with conn.transaction(), conn.cursor() as cur:
                cur.execute("SET LOCAL synchronous_commit = off")
                if update.reset:
                    cur.execute("DELETE FROM map_tiles WHERE stream = %s", (update.stream,))
                cur.execute(
                    "INSERT INTO map_streams VALUES (%s, %s, %s) ON CONFLICT (stream) DO UPDATE SET "
                    "tile_m = excluded.tile_m, last_seq = excluded.last_seq",
                    (update.stream, update.tile_m, update.seq),
                )
                if gone:
                    cur.executemany("DELETE FROM map_tiles WHERE stream = %s AND ix = %s AND iy = %s", gone)
                if kept:
                    cur.executemany(
                        "INSERT INTO map_tiles VALUES (%s, %s, %s, %s, %s, %s, %s, %s, %s, %s, %s) "
                        "ON CONFLICT (stream, ix, iy) DO UPDATE SET voxels = excluded.voxels, x_min = excluded.x_min, "
                        "y_min = excluded.y_min, z_min = excluded.z_min, x_max = excluded.x_max, "
                        "y_max = excluded.y_max, z_max = excluded.z_max, data = excluded.data",
                        kept,
                    )

        self.pool.run(tx)

    def delete_stream(self, stream: str) -> int:
        """The stream's map gone (`occvo store delete`); the tiles deleted."""

        def tx(conn):
            with conn.transaction():
                n = conn.execute("DELETE FROM map_tiles WHERE stream = %s", (stream,)).rowcount
                conn.execute("DELETE FROM map_streams WHERE stream = %s", (stream,))
                return n

        return self.pool.run(tx)

    def streams(self) -> list[str]:
        return self.pool.run(
            lambda conn: [r[0] for r in conn.execute("SELECT stream FROM map_streams ORDER BY stream")]
        )

    def tiles(
        self, stream: str, ix: int | None = None, iy: int | None = None, bounds: Bounds = None, limit: int | None = None
    ) -> list[tuple[int, int, bytes]]:
        """Encoded tiles of a stream: the one at (ix, iy) when both are given, else the first `limit` within bounds."""
        where, args = ["stream = %s"], [stream]
        if ix is not None and iy is not None:
            where += ["ix = %s", "iy = %s"]
            args += [ix, iy]
        if bounds is not None:
            for col, op, v in (
                ("ix", ">=", bounds.ix_min),
                ("ix", "<=", bounds.ix_max),
                ("iy", ">=", bounds.iy_min),
                ("iy", "<=", bounds.iy_max),
            ):
                if v is not None:
                    where.append(f"{col} {op} %s")
                    args.append(v)
        sql = f"SELECT ix, iy, data FROM map_tiles WHERE {' AND '.join(where)} ORDER BY ix, iy LIMIT %s"
        rows = self.pool.run(lambda conn: conn.execute(sql, [*args, limit], binary=True).fetchall())
        return [(int(x), int(y), bytes(d)) for x, y, d in rows]

    def info(self, stream: str) -> MapInfo | None:
        def read(conn):
            with conn.transaction():  # one view for the three reads
                conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ")
                row = conn.execute("SELECT tile_m, last_seq FROM map_streams WHERE stream = %s", (stream,)).fetchone()
                if row is None:
                    return None
                agg = conn.execute(
                    "SELECT COALESCE(SUM(voxels), 0), MIN(x_min), MIN(y_min), MIN(z_min), MAX(x_max), MAX(y_max), "
                    "MAX(z_max) FROM map_tiles WHERE stream = %s",
                    (stream,),
                ).fetchone()
                tiles = conn.execute("SELECT ix, iy FROM map_tiles WHERE stream = %s", (stream,)).fetchall()
            return row, agg, tiles

        got = self.pool.run(read)
        if got is None:
            return None
        row, agg, tiles = got
        lo, hi = (agg[1:4], agg[4:7]) if tiles else (None, None)
        return _info(stream, row[0], row[1], [tuple(t) for t in tiles], int(agg[0]), lo, hi)

    def close(self) -> None:
        self.pool.close()
