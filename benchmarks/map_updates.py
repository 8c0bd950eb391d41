"""What a frame's map update costs, step by step: the registration worker's part (the changed map region copied,
cut into tiles, built and encoded as a MapUpdate) and the map service's (decoded, each tile encoded, stored), run in
one process over a real scene's frames.

    python benchmarks/map_updates.py [--scene scene-0268] [--store]

--store keeps the tiles in a SQLite map store (as the deployed map service), else in memory. Prints the median ms of
each step over the frames after the first, and the update's tiles, voxels and bytes."""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from _common import SAMPLE

from occvo_core import OccVO
from occvo_core.datasets.occvo_release import OccVOReleaseScene
from occvo_core.map_tiles import changed_tiles, retile_region
from occvo_core.working_map import changed_map
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import MapUpdate
from occvo_services.registration.map_output import map_update
from occvo_services.store.factory import open_map_store

DATA = SAMPLE / "occupancy"
TILE_M = 20.0  # the workers' default tile_m


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="scene-0268")
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--store", action="store_true", help="a SQLite map store, as deployed")
    args = ap.parse_args(argv)
    vo, tiles, steps, sizes = OccVO(), {}, {}, []
    with tempfile.TemporaryDirectory() as tmp:
        store = open_map_store(Path(tmp) / "map.sqlite" if args.store else None)
        for seq, frame in enumerate(OccVOReleaseScene(args.data / args.scene)):
            vo.step(frame)
            watch = [time.perf_counter()]
            region, *cut = changed_map(vo, TILE_M)
            watch.append(time.perf_counter())
            new, dirty = retile_region(tiles, lambda *_, cut=cut: cut, region, TILE_M)
            old = {k: tiles[k] for k in dirty if k in tiles}
            changed = dict(new) if seq == 0 else changed_tiles(old, {k: new[k] for k in dirty if k in new})
            tiles = new
            watch.append(time.perf_counter())
            update = map_update("s", seq, seq == 0, TILE_M, changed)
            data = encode(update, 1 << 30)
            watch.append(time.perf_counter())
            received = decode(data, MapUpdate, 1 << 30)
            store.apply(received, [encode(t, 1 << 30) for t in received.tiles])
            watch.append(time.perf_counter())
            for name, t0, t1 in zip(("copy", "cut", "build+encode", "decode+encode+store"), watch, watch[1:]):
                steps.setdefault(name, []).append((t1 - t0) * 1000.0)
            sizes.append((len(update.tiles), sum(len(p) for p, _ in changed.values()), len(data)))
        store.close()
    print(f"{args.scene}, map store {'sqlite' if args.store else 'memory'}: median ms a frame (frames after the first)")
    for name, ms in steps.items():
        print(f"  {name:<22}{np.median(ms[1:]):8.2f}")
    tiles_n, voxels, size = np.median(np.array(sizes[1:]), axis=0)
    print(f"  update: {tiles_n:.0f} tiles, {voxels:.0f} voxels, {size / 1e6:.2f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
