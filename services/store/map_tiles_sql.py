"""The map service's tile SQL, written once for SQLite (services/store/map_tiles.py) and PostgreSQL
(services/store/map_tiles_pg.py): statements with `?` for a parameter, rendered by the database's dialect; `cols`
names the bounds' columns (SQLite's xmin..zmax, PostgreSQL's x_min..z_max: its system columns take xmin and xmax)."""

from __future__ import annotations

from occvo_schemas.models import MapUpdate

SQLITE_BOUNDS = ("xmin", "ymin", "zmin", "xmax", "ymax", "zmax")
POSTGRES_BOUNDS = ("x_min", "y_min", "z_min", "x_max", "y_max", "z_max")
MAP_STREAM = (
    "INSERT INTO map_streams (stream, tile_m, last_seq) VALUES (?, ?, ?) "
    "ON CONFLICT (stream) DO UPDATE SET tile_m = excluded.tile_m, last_seq = excluded.last_seq"
)


def apply(q, cols: tuple[str, ...], update: MapUpdate, rows: list):
    """fn(cur) writing an update's tiles (services/store/map_tiles._tile_rows): a reset deletes the stream's tiles
    first; an empty tile deletes that tile."""
    gone = [(update.stream, ix, iy) for ix, iy, n, *_ in rows if n == 0]
    kept = [(update.stream, ix, iy, n, *lo, *hi, data) for ix, iy, n, lo, hi, data in rows if n]
    upsert = (
        "INSERT INTO map_tiles VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?) ON CONFLICT (stream, ix, iy) DO UPDATE SET "
        + ", ".join(f"{c} = excluded.{c}" for c in ("voxels", *cols, "data"))
    )

    def tx(cur) -> None:
        if update.reset:
            cur.execute(q("DELETE FROM map_tiles WHERE stream = ?"), (update.stream,))
        cur.execute(q(MAP_STREAM), (update.stream, update.tile_m, update.seq))
        if gone:
            cur.executemany(q("DELETE FROM map_tiles WHERE stream = ? AND ix = ? AND iy = ?"), gone)
        if kept:
            cur.executemany(q(upsert), kept)

    return tx


def delete_stream(q, stream: str):
    """fn(cur) deleting the stream's map; the tiles deleted."""

    def tx(cur) -> int:
        n = cur.execute(q("DELETE FROM map_tiles WHERE stream = ?"), (stream,)).rowcount
        cur.execute(q("DELETE FROM map_streams WHERE stream = ?"), (stream,))
        return n

    return tx


def tiles(stream: str, ix: int | None, iy: int | None, bounds, limit: int | None) -> tuple[str, list]:
    """(statement, args) reading the encoded tiles of a stream: the one at (ix, iy) when both are given, else the
    first `limit` within bounds."""
    where, args = ["stream = ?"], [stream]
    if ix is not None and iy is not None:
        where += ["ix = ?", "iy = ?"]
        args += [ix, iy]
    if bounds is not None:
        for col, op, v in (
            ("ix", ">=", bounds.ix_min),
            ("ix", "<=", bounds.ix_max),
            ("iy", ">=", bounds.iy_min),
            ("iy", "<=", bounds.iy_max),
        ):
            if v is not None:
                where.append(f"{col} {op} ?")
                args.append(v)
    sql = f"SELECT ix, iy, data FROM map_tiles WHERE {' AND '.join(where)} ORDER BY ix, iy"
    return (sql, args) if limit is None else (sql + " LIMIT ?", [*args, limit])


def info(q, cols: tuple[str, ...], stream: str):
    """fn(cur) -> ((tile_m, last_seq), (voxels, *mins, *maxs), [(ix, iy)]) of a stream, or None; run in one view."""
    lo, hi = ", ".join(f"MIN({c})" for c in cols[:3]), ", ".join(f"MAX({c})" for c in cols[3:])

    def read(cur):
        row = cur.execute(q("SELECT tile_m, last_seq FROM map_streams WHERE stream = ?"), (stream,)).fetchone()
        if row is None:
            return None
        agg = cur.execute(
            q(f"SELECT COALESCE(SUM(voxels), 0), {lo}, {hi} FROM map_tiles WHERE stream = ?"), (stream,)
        ).fetchone()
        return row, agg, cur.execute(q("SELECT ix, iy FROM map_tiles WHERE stream = ?"), (stream,)).fetchall()

    return read
