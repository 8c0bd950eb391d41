"""Service pipeline benchmark (router in this process, the three workers as separate processes, loopback).

    python benchmarks/pipeline.py [--repeats 2] [--scenes scene-0101 scene-0268] [--output results.json]

Prints medians over the repeats of:
  - end-to-end frames/s replaying each real scene (lossless, window of 4 frames in flight);
  - pipeline efficiency = throughput x slowest stage time (mean per-frame busy time of the slowest worker); goal >= 0.9;
  - per-hop transport latency p50/p99 of a 30k-voxel occupancy frame, publisher -> router -> subscriber, including
    encode and decode, for the exact (float64) and the compact (voxel index) encodings; goal p50 <= 5 ms;
  - tile query p50/p99 (one 20 m tile, client -> router -> map service -> client); goal p50 <= 10 ms.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
warnings.filterwarnings("ignore", category=RuntimeWarning)

from occvo_core.grid import OCC3D_GRID  # noqa: E402
from occvo_schemas import keys  # noqa: E402
from occvo_schemas.codec import decode, encode  # noqa: E402
from occvo_schemas.models import OccupancyFrameMsg, SparseOccupancy  # noqa: E402
from occvo_services.client import OccVOClient  # noqa: E402
from occvo_services.commands.replay import replay  # noqa: E402
from occvo_services.local import LocalService  # noqa: E402
from occvo_services.runtime import free_port, open_router, open_session  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared/data/occvo-sample/occupancy"


def hop_latency(n: int = 300, voxels: int = 30000, exact: bool = True) -> tuple[np.ndarray, int]:
    """ms from encode+put on one session to decoded message on another, through a router; one message at a time."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(ep)
    pub_s, sub_s = open_session(ep), open_session(ep)
    rng = np.random.default_rng(0)
    idx = rng.integers(0, OCC3D_GRID.shape, (voxels, 3))
    occ = SparseOccupancy.from_points(OCC3D_GRID.centres_of(idx), rng.integers(0, 17, voxels), OCC3D_GRID, exact=exact)
    msg = OccupancyFrameMsg(stream="bench", seq=0, stamp=0.0, source="replay", occupancy=occ)
    got = threading.Event()
    lat = []

    def on(sample):
        m = decode(sample.payload.to_bytes(), OccupancyFrameMsg)
        lat.append((time.perf_counter() - t0) * 1000.0)
        assert len(m.occupancy) == voxels
        got.set()

    sub = sub_s.declare_subscriber(keys.occupancy("bench"), on)
    pub = pub_s.declare_publisher(keys.occupancy("bench"), congestion_control=zenoh.CongestionControl.BLOCK)
    time.sleep(0.5)
    for i in range(n + 20):  # the first 20 warm the path up
        got.clear()
        t0 = time.perf_counter()
        pub.put(encode(msg.model_copy(update={"seq": i})))
        if not got.wait(5):
            raise RuntimeError("hop benchmark: message lost")
    sub.undeclare()
    pub.undeclare()
    pub_s.close()
    sub_s.close()
    router.close()
    return np.array(lat[20:]), len(encode(msg))


def run_scene(scene_dir: Path, window: int) -> dict:
    from occvo_core.datasets.occvo_release import OccVOReleaseScene

    scene = OccVOReleaseScene(scene_dir)
    with LocalService(quiet=True) as svc, OccVOClient(svc.endpoint, scene.name) as client:
        out = replay(client, scene, window=window)
        stats = {h.role: h for h in client.stats()}
        busy = {role: h.stages["stage_total"].mean_ms for role, h in stats.items() if "stage_total" in h.stages}
        slowest = max(busy, key=busy.get)
        info = client.map_info()
        ix, iy = info.tiles[len(info.tiles) // 2]
        tile_voxels = client.tile(ix, iy).points.shape[0]
        for _ in range(20):
            client.tile(ix, iy)
        tq = []
        for _ in range(200):
            t0 = time.perf_counter()
            client.tile(ix, iy)
            tq.append((time.perf_counter() - t0) * 1000.0)
        hops = {k: v for k, v in out["pose_msgs"][len(scene) - 1].timings_ms.items() if k.endswith("_hop")}
    return {
        "scene": scene.name,
        "frames": out["frames"],
        "poses": out["poses"],
        "fps": out["fps"],
        "stage_mean_ms": busy,
        "slowest": slowest,
        "efficiency": out["fps"] * busy[slowest] / 1000.0,
        "tile_query_p50_ms": float(np.percentile(tq, 50)),
        "tile_query_p99_ms": float(np.percentile(tq, 99)),
        "tile_voxels": int(tile_voxels),
        "map_voxels": info.voxel_count,
        "last_frame_hops_ms": hops,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["scene-0101", "scene-0268"])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--window", type=int, default=4)
    ap.add_argument("--hop-messages", type=int, default=300)
    ap.add_argument("--output")
    args = ap.parse_args(argv)

    results = {"hop": {}, "scenes": {}}
    for exact in (True, False):
        name = "exact_float64" if exact else "compact_indices"
        runs = [hop_latency(args.hop_messages, exact=exact) for _ in range(args.repeats)]
        size = runs[0][1]
        runs = [r for r, _ in runs]
        p50 = float(np.median([np.percentile(r, 50) for r in runs]))
        p99 = float(np.median([np.percentile(r, 99) for r in runs]))
        results["hop"][name] = {"p50_ms": p50, "p99_ms": p99, "bytes": size}
        print(
            f"hop 30k voxels {name:16s} {size / 1e6:5.2f} MB  p50 {p50:6.2f} ms  p99 {p99:6.2f} ms  (goal p50 <= 5 ms)",
            flush=True,
        )

    for name in args.scenes:
        d = DATA / name
        if not d.is_dir():
            print(f"{name}: not found at {d}, skipped")
            continue
        runs = [run_scene(d, args.window) for _ in range(args.repeats)]
        med = {
            k: float(np.median([r[k] for r in runs]))
            for k in ("fps", "efficiency", "tile_query_p50_ms", "tile_query_p99_ms")
        }
        stage = {
            role: float(np.median([r["stage_mean_ms"].get(role, np.nan) for r in runs]))
            for role in runs[0]["stage_mean_ms"]
        }
        results["scenes"][name] = {"median": med, "stage_mean_ms": stage, "runs": runs}
        print(
            f"{name}: {runs[0]['frames']} frames  {med['fps']:.2f} frames/s  efficiency {med['efficiency']:.3f} (goal >= 0.9)  "
            f"stage mean ms {json.dumps({k: round(v, 1) for k, v in stage.items()})}  "
            f"tile query p50 {med['tile_query_p50_ms']:.2f} ms p99 {med['tile_query_p99_ms']:.2f} ms (goal p50 <= 10 ms)",
            flush=True,
        )
    if args.output:
        Path(args.output).write_text(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
