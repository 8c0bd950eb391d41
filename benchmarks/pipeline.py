"""The service against the odometry inside it: real scenes through the router and the three worker processes (store
on) beside offline OccVO on the same frames, in the same run.

    python benchmarks/pipeline.py [--repeats 3] [--scenes scene-0101 scene-0268] [--output results.json]
        [--registration-args "--after-pose-nice 0"]

Per scene, medians over the repeats of (each goal read on one repeat's offline and service runs side by side, the
host's speed drifting between repeats):
  - offline_fps: OccVO.step (all cores, as `occvo run`) over the scene's frames, per repeat;
  - service_fps: lossless replay (window of 4 frames in flight) through the router, the inference, registration and
    map workers, both stores on, from the first frame sent to the last pose received (the frames read before, as
    offline's are); ratio = service / offline
    (goal >= 0.8); poses checked equal to the offline ones bit for bit;
  - pose latency p50/p99 at 2 Hz (client send to pose arrival) beside the offline registration time a frame (the
    whole step, median and p99; goal p50 <= median + 10 ms, p99 <= 2 x p99);
  - a stage row: the offline stages of the same frames beside the service's (the pose's timings_ms medians, the
    worker stats' p50 for the work after the pose), and the poses' stages at RATE_HZ (where the latency goes);
  - tile query p50/p99 (one 20 m tile, client -> router -> map service -> client);
  - CPU a frame (user + system) of the offline run and, over the lossless replay, of each service process: what
    the service adds to the odometry's work on the same cores, and the ratio that leaves possible at best
    (offline CPU over offline plus added, when the odometry's kernels already keep every core busy).
And the per-hop transport latency p50/p99 of a 30k-voxel occupancy frame, publisher -> router -> subscriber,
including encode and decode: a recorded frame's exact coordinates as float64 points or as indices with axes (what
replay sends), and indices only (--hop-messages 0 skips it).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import psutil
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
warnings.filterwarnings("ignore", category=RuntimeWarning)

from occvo_core import OccVO  # noqa: E402
from occvo_core.datasets.occvo_release import OccVOReleaseScene  # noqa: E402
from occvo_core.grid import OCC3D_GRID  # noqa: E402
from occvo_schemas import keys  # noqa: E402
from occvo_schemas.codec import decode, encode  # noqa: E402
from occvo_schemas.models import Array, OccupancyFrameMsg, SparseOccupancy  # noqa: E402
from occvo_services.client import OccVOClient  # noqa: E402
from occvo_services.commands.replay import replay  # noqa: E402
from occvo_services.local import LocalService  # noqa: E402
from occvo_services.sessions import free_port, open_router, open_session  # noqa: E402

DATA = Path(__file__).resolve().parents[2] / "shared/data/occvo-sample/occupancy"
RATE_HZ = 2.0  # the paper's camera rate
# the service's own stages, in the order a frame meets them (pose timings_ms keys; after the pose: worker stats)
SERVICE_STAGES = (
    "camera_hop",
    "camera_decode",
    "inference_queue",
    "inference",
    "occupancy_hop",
    "decode",
    "registration_queue",
    "after_pose_wait",
    "validate",
    "registration",
    "store_commit",
    "core_wait",
)
AFTER_POSE_STAGES = (  # the after-pose thread's (the next frame waits for it), then the map thread's
    "pose_encode",
    "complete",
    "map_restore",
    "map_evict",
    "map_extract",
    "after_pose_store",
    "map_wait",
    "frame_after_pose",
    "stage_total",
    "tiling",
    "map_publish",
)


def hop_latency(n: int = 300, voxels: int = 30000, encoding: str = "axes") -> tuple[np.ndarray, int]:
    """ms from encode+put on one session to decoded message on another, through a router; one message at a time.
    encoding: a recorded frame's exact coordinates as float64 "points" or as indices with "axes" (what replay
    sends), or "voxels" (indices only: the network's output)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(ep)
    pub_s, sub_s = open_session(ep), open_session(ep)
    rng = np.random.default_rng(0)
    idx = rng.integers(0, OCC3D_GRID.shape, (voxels, 3))
    wobble = rng.integers(-3, 4, (3, max(OCC3D_GRID.shape))) * 2.0**-48  # the release's last bits, one value an index
    points = OCC3D_GRID.centres_of(idx) + np.stack([wobble[a, idx[:, a]] for a in range(3)], axis=1)
    labels = rng.integers(0, 17, voxels)
    if encoding == "points":
        occ = SparseOccupancy(points=Array.from_numpy(points), labels=Array.from_numpy(labels.astype(np.uint8)))
    else:
        occ = SparseOccupancy.from_points(points, labels, OCC3D_GRID, exact=encoding == "axes")
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


def offline(frames: list) -> dict:
    """One run of OccVO over the frames as `occvo run` does (all cores): frames/s, each frame's step time, the
    stages' medians and the poses."""
    vo = OccVO(threads=0)
    step_ms, stages = [], {}
    t_run, cpu_run = time.perf_counter(), time.process_time()
    for frame in frames:
        t0 = time.perf_counter()
        result = vo.step(frame)
        step_ms.append((time.perf_counter() - t0) * 1000.0)
        for k, v in result.timings_ms.items():
            stages.setdefault(k, []).append(v)
    seconds = time.perf_counter() - t_run
    return {
        "fps": len(frames) / seconds,
        "cpu_ms": (time.process_time() - cpu_run) * 1000.0 / len(frames),
        "step_ms": step_ms[1:],  # the first frame only seeds the map
        "stages": _medians(stages),
        "poses": np.array(vo.poses),
    }


def _medians(timings: dict[str, list[float]]) -> dict[str, float]:
    """Stage -> its median over the frames, the first left out when there are more (it only seeds the map)."""
    return {k: float(np.median(v[1:] if len(v) > 1 else v)) for k, v in timings.items()}


def _stage_medians(pose_msgs: dict) -> dict[str, float]:
    """Stage -> its median over the poses (PoseEstimate.timings_ms)."""
    timings = {}
    for pose in pose_msgs.values():
        for k, v in pose.timings_ms.items():
            timings.setdefault(k, []).append(v)
    return _medians(timings)


def service(name: str, frames: list, store_dir: Path, window: int, registration_args: list[str]) -> dict:
    """The scene's frames through the router and the three worker processes, both stores on: a lossless replay as
    fast as the pipeline takes, then one at RATE_HZ. The frames are read before, as offline's are."""
    args = {
        "registration": ["--store-path", str(store_dir / "occvo.sqlite"), *registration_args],
        "map": ["--store-path", str(store_dir / "map.sqlite")],
    }
    with LocalService(quiet=True, worker_args=args) as svc, OccVOClient(svc.endpoint, name) as client:
        procs = {"router + client": psutil.Process()} | {r: psutil.Process(p.pid) for r, p in svc.procs.items()}
        cpu0 = {r: sum(p.cpu_times()[:2]) for r, p in procs.items()}
        fast = replay(client, frames, window=window)
        cpu = {r: (sum(p.cpu_times()[:2]) - cpu0[r]) * 1000.0 / len(frames) for r, p in procs.items()}
        health = {h.role: h for h in client.stats()}
        timings = _stage_medians(fast["pose_msgs"])
        info = client.map_info()
        ix, iy = info.tiles[len(info.tiles) // 2]
        for _ in range(20):
            client.tile(ix, iy)
        tq = []
        for _ in range(200):
            t0 = time.perf_counter()
            client.tile(ix, iy)
            tq.append((time.perf_counter() - t0) * 1000.0)
        with OccVOClient(svc.endpoint, f"{name}-live") as live_client:  # a new stream: nothing is a resend
            live = replay(live_client, frames, rate_hz=RATE_HZ, window=len(frames))
            arrived = live_client.arrived
            latency = [(arrived[s] - t) * 1000.0 for s, t in enumerate(live["sent_at"]) if s in arrived]
            live_timings = _stage_medians(live["pose_msgs"])
    reg = health["registration"].stages
    return {
        "fps": fast["fps"],
        "cpu_ms": cpu,
        "poses": fast["poses"],
        "errors": fast["errors"] + live["errors"],
        "trajectory": fast["trajectory"],
        "timings": timings,
        "after_pose": {k: reg[k].p50_ms for k in AFTER_POSE_STAGES if k in reg},
        "worker_stats_p50": {
            role: {k: s.p50_ms for k, s in h.stages.items()} for role, h in health.items() if h.stages
        },
        "latency_ms": latency,
        "latency_timings": live_timings,
        "tile_query_ms": tq,
    }


def run_scene(scene_dir: Path, repeats: int, window: int, registration_args: list[str]) -> dict:
    scene = OccVOReleaseScene(scene_dir)
    frames = [scene[i] for i in range(len(scene))]
    offline(frames[:3])  # compile / warm caches
    runs = []
    for _ in range(repeats):
        off = offline(frames)  # beside each service run: the same machine state
        with tempfile.TemporaryDirectory(prefix="occvo-pipeline-") as tmp:
            svc = service(scene.name, frames, Path(tmp), window, registration_args)
        runs.append((off, svc))
    offs, svcs = [r[0] for r in runs], [r[1] for r in runs]
    offline_fps = float(np.median([o["fps"] for o in offs]))
    service_fps = float(np.median([s["fps"] for s in svcs]))
    step_med = float(np.median([np.median(o["step_ms"]) for o in offs]))
    step_p99 = float(np.median([np.percentile(o["step_ms"], 99) for o in offs]))
    lat_p50 = float(np.median([np.percentile(s["latency_ms"], 50) for s in svcs]))
    lat_p99 = float(np.median([np.percentile(s["latency_ms"], 99) for s in svcs]))
    # the host's speed drifts between runs: each goal is read on one repeat's offline and service runs side by
    # side, then the median over the repeats
    ratios = [s["fps"] / o["fps"] for o, s in zip(offs, svcs)]
    p50_margins = [np.percentile(s["latency_ms"], 50) - np.median(o["step_ms"]) for o, s in zip(offs, svcs)]
    p99_ratios = [np.percentile(s["latency_ms"], 99) / np.percentile(o["step_ms"], 99) for o, s in zip(offs, svcs)]
    ratio, p50_margin, p99_ratio = (float(np.median(v)) for v in (ratios, p50_margins, p99_ratios))
    identical = all(
        s["poses"] == len(frames) and np.array_equal(s["trajectory"], o["poses"]) for o, s in zip(offs, svcs)
    )
    offline_stages = {k: float(np.median([o["stages"][k] for o in offs])) for k in offs[0]["stages"]}
    offline_cpu = float(np.median([o["cpu_ms"] for o in offs]))
    service_cpu = {r: float(np.median([s["cpu_ms"][r] for s in svcs])) for r in svcs[0]["cpu_ms"]}
    added_cpu = (
        sum(service_cpu.values()) - service_cpu["registration"] + max(0.0, service_cpu["registration"] - offline_cpu)
    )
    service_stages = {k: float(np.median([s["timings"].get(k, np.nan) for s in svcs])) for k in svcs[0]["timings"]}
    service_stages |= {
        k: float(np.median([s["after_pose"].get(k, np.nan) for s in svcs])) for k in svcs[0]["after_pose"]
    }
    service_stages |= {  # complete()'s stages (loop closure, map update), from the worker's stats
        k: float(np.median([s["worker_stats_p50"]["registration"].get(k, np.nan) for s in svcs]))
        for k in svcs[0]["worker_stats_p50"]["registration"]
        if k.startswith("complete.")
    }
    return {
        "frames": len(frames),
        "repeats": repeats,
        "offline_fps": offline_fps,
        "service_fps": service_fps,
        "ratio": ratio,
        "ratios": ratios,
        "latency_p50_over_offline_median_ms": p50_margin,
        "latency_p99_over_offline_p99": p99_ratio,
        "offline_registration_median_ms": step_med,
        "offline_registration_p99_ms": step_p99,
        "latency_p50_ms": lat_p50,
        "latency_p99_ms": lat_p99,
        "latency_rate_hz": RATE_HZ,
        "poses_identical": identical,
        "errors": int(sum(s["errors"] for s in svcs)),
        "goals": {
            "ratio >= 0.8": ratio >= 0.8,
            "latency p50 <= offline median + 10 ms": p50_margin <= 10.0,
            "latency p99 <= 2 x offline p99": p99_ratio <= 2.0,
        },
        "offline_stage_median_ms": offline_stages,
        "offline_cpu_ms": offline_cpu,
        "service_cpu_ms": service_cpu,
        "service_added_cpu_ms": added_cpu,
        "ratio_bound": offline_cpu / (offline_cpu + added_cpu),
        "service_stage_median_ms": service_stages,
        "worker_stats_p50_ms": svcs[0]["worker_stats_p50"],
        "latency_stage_median_ms": {  # the stages of the poses at RATE_HZ: where the latency goes
            k: float(np.median([s["latency_timings"].get(k, np.nan) for s in svcs])) for k in svcs[0]["latency_timings"]
        },
        "tile_query_p50_ms": float(np.median([np.percentile(s["tile_query_ms"], 50) for s in svcs])),
        "tile_query_p99_ms": float(np.median([np.percentile(s["tile_query_ms"], 99) for s in svcs])),
        "runs": [
            {"offline_fps": o["fps"], "service_fps": s["fps"], "latency_ms": s["latency_ms"]}
            for o, s in zip(offs, svcs)
        ],
    }


def print_scene(name: str, r: dict) -> None:
    print(
        f"\n{name}: {r['frames']} frames, {r['repeats']} runs (medians)\n"
        f"  offline {r['offline_fps']:.1f} frames/s   service {r['service_fps']:.1f} frames/s   ratio "
        f"{r['ratio']:.2f} (goal >= 0.8; by run {', '.join(f'{x:.2f}' for x in r['ratios'])})   poses bit-identical: "
        f"{r['poses_identical']}   errors {r['errors']}\n"
        f"  latency at {r['latency_rate_hz']:g} Hz p50 {r['latency_p50_ms']:.1f} ms p99 {r['latency_p99_ms']:.1f} ms"
        f"   offline registration median {r['offline_registration_median_ms']:.1f} ms "
        f"p99 {r['offline_registration_p99_ms']:.1f} ms; paired: p50 offline median "
        f"{r['latency_p50_over_offline_median_ms']:+.1f} ms, p99 {r['latency_p99_over_offline_p99']:.2f} x offline p99\n"
        f"  goals {json.dumps(r['goals'])}\n"
        f"  tile query p50 {r['tile_query_p50_ms']:.2f} ms p99 {r['tile_query_p99_ms']:.2f} ms",
        flush=True,
    )
    off, svc = r["offline_stage_median_ms"], r["service_stage_median_ms"]
    print(f"  {'stage (median ms a frame)':<34}{'offline':>9}{'service':>9}")
    for k in SERVICE_STAGES:
        if k == "registration":  # the odometry's own stages, each beside its service twin
            for s in off:
                twin = next((t for t in (f"registration.{s}", f"complete.{s}") if t in svc), s)
                print(f"    {s:<32}{off[s]:>9.1f}{svc.get(twin, float('nan')):>9.1f}")
            print(f"  {'registration (through fine GICP)':<34}{'':>9}{svc.get(k, float('nan')):>9.1f}")
        elif k in svc:
            print(f"  {k:<34}{'':>9}{svc[k]:>9.1f}")
    print("  after the pose (worker stats p50):")
    for k in AFTER_POSE_STAGES:
        if k in svc:
            print(f"    {k:<32}{'':>9}{svc[k]:>9.1f}")
    cpu = ", ".join(f"{k} {v:.1f}" for k, v in r["service_cpu_ms"].items())
    print(
        f"  CPU a frame: offline {r['offline_cpu_ms']:.1f} ms; service {cpu} ms; the service adds "
        f"{r['service_added_cpu_ms']:.1f} ms: on cores the odometry keeps busy, ratio {r['ratio_bound']:.2f} at best"
    )
    live = r["latency_stage_median_ms"]
    print(f"  at {r['latency_rate_hz']:g} Hz, a pose's stages: " + ", ".join(f"{k} {v:.1f}" for k, v in live.items()))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["scene-0101", "scene-0268"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--window", type=int, default=4)
    ap.add_argument("--hop-messages", type=int, default=300, help="0: no hop latency measurement")
    ap.add_argument("--output")
    ap.add_argument(
        "--registration-args", default="", help='extra flags of the registration worker, e.g. "--after-pose-nice 0"'
    )
    args = ap.parse_args(argv)

    results = {"hop": {}, "scenes": {}}
    for name in ("points", "axes", "voxels") if args.hop_messages > 0 else ():
        runs = [hop_latency(args.hop_messages, encoding=name) for _ in range(args.repeats)]
        size = runs[0][1]
        runs = [r for r, _ in runs]
        p50 = float(np.median([np.percentile(r, 50) for r in runs]))
        p99 = float(np.median([np.percentile(r, 99) for r in runs]))
        results["hop"][name] = {"p50_ms": p50, "p99_ms": p99, "bytes": size}
        print(f"hop 30k voxels {name:16s} {size / 1e6:5.2f} MB  p50 {p50:6.2f} ms  p99 {p99:6.2f} ms", flush=True)

    for name in args.scenes:
        d = DATA / name
        if not d.is_dir():
            print(f"{name}: not found at {d}, skipped")
            continue
        results["scenes"][name] = r = run_scene(d, args.repeats, args.window, args.registration_args.split())
        print_scene(name, r)
    if args.output:
        Path(args.output).write_text(json.dumps(results, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
