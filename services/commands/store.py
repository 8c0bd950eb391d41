"""occvo store: the streams a store holds, one stream's trajectory exported, a stream deleted (SQLite or PostgreSQL,
the trajectory store and the map store alike). Delete a stream while no worker serves it (stopped, or the stream idle
past idle_stream_s): a worker holding it in memory would write it back."""

from __future__ import annotations

import datetime
from pathlib import Path

from occvo_cli.paths import out_file
from occvo_core.errors import ConfigError
from occvo_core.overwrite import check_replaceable
from occvo_services.commands._common import add_json, emit, stream_id


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("store", help="list, export and delete the streams of a store")
    sub = p.add_subparsers(dest="action", required=True, metavar="ACTION", help="list, export or delete")
    for name, what in (
        ("list", "every stream: client, last seq, poses, bytes, map tiles, start"),
        ("export", "a stream's stored trajectory as a TUM or KITTI file"),
        ("delete", "a stream's trajectory, journal, snapshots and map"),
    ):
        a = sub.add_parser(name, help=what)
        a.add_argument(
            "--store",
            metavar="URL",
            help="a SQLite file (path or sqlite:///path) or postgresql://user@host/db, no password here (default: "
            "$OCCVO_STORE_URL)",
        )
        a.add_argument("--store-url-file", metavar="FILE", help="a file readable by its owner only holding the URL")
        if name != "list":
            a.add_argument("stream", type=stream_id, help="the stream id")
        if name == "export":
            a.add_argument(
                "--out", type=out_file(kind=str), required=True, help="the file written (.kitti: KITTI rows, else TUM)"
            )
            a.add_argument(
                "--force",
                action="store_true",
                help="replace an existing --out file that occvo did not write (default: refused; docs/cli.md)",
            )
        add_json(a)
        a.set_defaults(func=run)


def _store_url(args) -> str:
    """The store as `occvo serve` takes it: --store (no password there), --store-url-file, OCCVO_STORE_URL."""
    from occvo_services.store.url import SECRET_WAYS, resolve

    url = resolve(args.store, args.store_url_file)
    if not url:
        raise ConfigError(f"no store given: --store URL, or {SECRET_WAYS}")
    return url


def _open(url: str):
    from occvo_services.store.factory import open_map_store, open_store
    from occvo_services.store.url import is_postgres_url, sqlite_path

    if not is_postgres_url(url) and not Path(sqlite_path(url)).is_file():
        raise ConfigError(f"--store {url}: no such store file")
    return open_store(url), open_map_store(url)


def run(args) -> int:
    from occvo_core.trajectory import write_kitti, write_tum
    from occvo_services.store.url import redact

    if args.action == "export":
        check_replaceable(args.out, "trajectory", "--out", args.force)
    url = _store_url(args)
    store, maps = _open(url)
    args.store = redact(url)  # as the messages below name it
    try:
        if args.action == "list":
            rows = []
            for stream in sorted(set(store.streams()) | set(maps.streams())):
                rec, sizes, info = store.record(stream), store.sizes(stream), maps.info(stream)
                usage = store.stream_usage(stream)
                rows.append(
                    {
                        "stream": stream,
                        "client": None if usage is None else usage[0],
                        "last_seq": None if rec is None else rec.last_seq,
                        "poses": sizes["poses_rows"],
                        "bytes": sum(v for k, v in sizes.items() if k.endswith("_bytes")),
                        "map_tiles": 0 if info is None else len(info.tiles),
                        "created": None if rec is None else rec.created,
                    }
                )
            text = "\n".join(
                f"{r['stream']}: client {r['client'] or '-'}, last seq {r['last_seq']}, {r['poses']} poses, "
                f"{r['bytes']} bytes, {r['map_tiles']} map tiles, started {_when(r['created'])}"
                for r in rows
            )
            emit(args, {"streams": rows}, text or "no streams")
        elif args.action == "export":
            import numpy as np

            poses = store.poses(args.stream)
            if not poses:
                raise ConfigError(f"stream {args.stream!r} has no stored poses in {args.store}")
            matrices, stamps = np.array([p.pose for p in poses]), np.array([p.stamp for p in poses])
            if args.out.endswith(".kitti"):
                write_kitti(args.out, matrices)
            else:
                write_tum(args.out, matrices, stamps)
            emit(
                args, {"stream": args.stream, "poses": len(poses), "out": args.out}, f"{len(poses)} poses -> {args.out}"
            )
        else:
            if store.record(args.stream) is None and maps.info(args.stream) is None:
                raise ConfigError(f"stream {args.stream!r} is not in {args.store}")
            n, tiles = store.delete_stream(args.stream), maps.delete_stream(args.stream)
            emit(
                args,
                {"stream": args.stream, "poses_deleted": n, "map_tiles_deleted": tiles},
                f"stream {args.stream} deleted: {n} poses, {tiles} map tiles",
            )
    finally:
        store.close()
        maps.close()
    return 0


def _when(t: float | None) -> str:
    return "-" if t is None else datetime.datetime.fromtimestamp(t, datetime.UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
