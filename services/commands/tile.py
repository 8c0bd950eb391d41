"""occvo tile X Y: one map tile (by tile index, or --metres for the tile holding world point X, Y)."""

from __future__ import annotations

import math

import numpy as np

from occvo_core.errors import ConfigError
from occvo_core.grid import CLASS_NAMES
from occvo_core.overwrite import check_replaceable
from occvo_services.commands._common import add_connection, add_json, client, emit


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("tile", help="query one map tile")
    p.add_argument("x", type=float, help="tile index along x (with --metres: a world x in metres)")
    p.add_argument("y", type=float, help="tile index along y (with --metres: a world y in metres)")
    add_connection(p)
    p.add_argument("--metres", action="store_true", help="X Y are world coordinates, not tile indices")
    p.add_argument(
        "--out", "--output", dest="out", help="save the tile as an (M,4) x,y,z,label .npy (--output: the old name)"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out file that occvo did not write (default: refused; docs/cli.md)",
    )
    add_json(p)
    p.set_defaults(func=run)


def run(args) -> int:
    if not args.metres and not (args.x.is_integer() and args.y.is_integer()):
        raise ConfigError(f"tile indices are integers, got {args.x:g} {args.y:g}: pass --metres for world coordinates")
    if args.out and not args.out.endswith(".npy"):
        args.out += ".npy"  # where np.save writes it
    check_replaceable(args.out, "npy", "--out", args.force)
    with client(args) as c:
        if args.metres:
            tile_m = c.map_info().tile_m
            ix, iy = math.floor(args.x / tile_m), math.floor(args.y / tile_m)
        else:
            ix, iy = int(args.x), int(args.y)
        t = c.tile(ix, iy)  # ServiceError (tile_not_found, ...): one line, exit code 1
    pts, labels = t.points.to_numpy(), t.labels.to_numpy()
    if args.out:
        np.save(args.out, np.column_stack([pts, labels.astype(np.float64)]))
    counts = np.bincount(labels, minlength=len(CLASS_NAMES))
    record = {
        "stream": t.stream,
        "ix": t.ix,
        "iy": t.iy,
        "tile_m": t.tile_m,
        "seq": t.seq,
        "voxels": len(pts),
        "labels": {CLASS_NAMES[c]: int(n) for c, n in enumerate(counts) if n},
    }
    text = f"tile ({t.ix}, {t.iy}) of stream {t.stream}, {t.tile_m} m, frame {t.seq}: {len(pts)} voxels\n" + "\n".join(
        f"  {name}: {n}" for name, n in record["labels"].items()
    )
    emit(args, record, text)
    return 0
