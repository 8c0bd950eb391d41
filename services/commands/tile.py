"""occvo tile X Y: one map tile (by tile index, or --metres for the tile holding world point X, Y)."""

from __future__ import annotations

import json
import math

import numpy as np

from occvo_core.grid import CLASS_NAMES
from services.client import OccVOClient, ServiceError
from services.commands._common import add_connection, endpoint


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("tile", help="query one map tile")
    p.add_argument("x", type=float)
    p.add_argument("y", type=float)
    add_connection(p)
    p.add_argument("--metres", action="store_true", help="X Y are world coordinates, not tile indices")
    p.add_argument("--output", help="save the tile as an (M,4) x,y,z,label .npy")
    p.set_defaults(func=run)


def run(args) -> int:
    with OccVOClient(endpoint(args), stream=args.stream) as client:
        if args.metres:
            tile_m = client.map_info().tile_m
            ix, iy = math.floor(args.x / tile_m), math.floor(args.y / tile_m)
        else:
            ix, iy = int(args.x), int(args.y)
        try:
            t = client.tile(ix, iy)
        except ServiceError as exc:
            print(json.dumps({"error": str(exc)}))
            return 1
    pts, labels = t.points.to_numpy(), t.labels.to_numpy()
    if args.output:
        np.save(args.output, np.column_stack([pts, labels.astype(np.float64)]))
    counts = np.bincount(labels, minlength=len(CLASS_NAMES))
    print(json.dumps({"stream": t.stream, "ix": t.ix, "iy": t.iy, "tile_m": t.tile_m, "seq": t.seq, "voxels": len(pts),
                      "labels": {CLASS_NAMES[c]: int(n) for c, n in enumerate(counts) if n}}))
    return 0
