"""The service against the odometry inside it: real scenes through the router and the three worker processes (store
on) beside offline OccVO on the same frames, in the same run.

    python benchmarks/pipeline.py [--repeats 10] [--live-runs 2] [--scenes scene-0101 scene-0268]
        [--output results.json] [--registration-args "--after-pose-nice 0"]

Per scene, in one service (a 3-frame stream first: the workers' first use of a stream's path, as offline's warm-up):
  - `repeats` lossless replays (window of 4 frames in flight, each a new stream) through the router, the inference,
    registration and map workers, both stores on, from the first frame sent to the last pose received (the frames
    read before, as offline's are), each between two offline runs (OccVO.step on all cores, as `occvo run`). The
    host's speed drifts within seconds, so each replay's ratio is its frames/s over the mean of its two neighbours';
    ratio = the median of those (goal >= 0.9); poses checked equal to the offline ones bit for bit;
  - pose latency p50/p99 at 2 Hz (client send to pose arrival; `live_runs` streams, each between two offline runs
    too) beside the time a frame of the offline runs beside it (the whole step, median and p99; goal p50 <= median
    + 10 ms, p99 <= 2 x p99; the medians over the streams), and beside an offline run at 2 Hz (its steps start on
    idle cores, as the service's do);
  - a stage row: the offline stages of the same frames beside the service's (the pose's timings_ms medians, the
    worker stats' p50 for the work after the pose), and the poses' stages at RATE_HZ (where the latency goes);
  - tile query p50/p99 (one 20 m tile, client -> router -> map service -> client);
  - CPU a frame (user + system) of the offline run and, over the lossless replays, of each service process: what
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
import time
import warnings
from pathlib import Path

import numpy as np
import psutil

warnings.filterwarnings("ignore", category=RuntimeWarning)

from _common import SAMPLE, print_scene  # noqa: E402
from _hop_latency import hop_latency  # noqa: E402

from occvo_core import OccVO  # noqa: E402
from occvo_core.datasets.occvo_release import OccVOReleaseScene  # noqa: E402
from occvo_services.client import OccVOClient  # noqa: E402
from occvo_services.commands.replay import replay  # noqa: E402
from occvo_services.local import LocalService  # noqa: E402

RATE_HZ = 2.0  # the paper's camera rate
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


def offline(frames: list, rate_hz: float = 0.0) -> dict:
    """One run of OccVO over the frames as `occvo run` does (all cores): frames/s, each frame's step time, the
    stages' medians and the poses. rate_hz: a frame every 1/rate_hz s (the steps' times only then mean anything)."""
    vo = OccVO(threads=0)
    step_ms, stages = [], {}
    t_run, cpu_run = time.perf_counter(), time.process_time()
    for i, frame in enumerate(frames):
        if rate_hz > 0:
            time.sleep(max(0.0, t_run + i / rate_hz - time.perf_counter()))
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


def service(name: str, frames: list, store_dir: Path, args) -> dict:
    """The scene's frames through the router and the three worker processes, both stores on, in one service: a short
    stream first (the workers' first use of a stream's path, as offline's warm-up), then `repeats` lossless replays,
    each a new stream, with an offline run before and after each (the host's speed drifts within seconds: each
    replay is read against the mean of its two neighbours), then `live_runs` streams at RATE_HZ. The frames are
    read before, as offline's are."""
    worker_args = {
        "registration": ["--store-path", str(store_dir / "occvo.sqlite"), *args.registration_args.split()],
        "map": ["--store-path", str(store_dir / "map.sqlite")],
    }
    fast, offs, stats = [], [], {}
    with LocalService(quiet=True, worker_args=worker_args) as svc, OccVOClient(svc.endpoint, f"{name}-warm") as warm:
        replay(warm, frames[:3], window=args.window)
        procs = {"router + client": psutil.Process()} | {r: psutil.Process(p.pid) for r, p in svc.procs.items()}
        cpu = dict.fromkeys(procs, 0.0)
        offs.append(offline(frames))
        for i in range(args.repeats):
            with OccVOClient(svc.endpoint, f"{name}-{i}") as client:
                cpu0 = {r: _cpu_s(p) for r, p in procs.items()}
                fast.append(replay(client, frames, window=args.window))
                for r, p in procs.items():
                    cpu[r] += (_cpu_s(p) - cpu0[r]) * 1000.0 / len(frames) / args.repeats
                stats = {h.role: h for h in client.stats()}  # the last replay's window of the workers' stats
            _quiet(procs)  # the last frame's work after its pose, its tiles, the store's checkpoint: not in offline's
            offs.append(offline(frames))
        with OccVOClient(svc.endpoint, f"{name}-0") as client:
            info = client.map_info()
            ix, iy = info.tiles[len(info.tiles) // 2]
            for _ in range(20):
                client.tile(ix, iy)
            tile_ms = []
            for _ in range(200):
                t0 = time.perf_counter()
                client.tile(ix, iy)
                tile_ms.append((time.perf_counter() - t0) * 1000.0)
        live, live_offs = [], [offs[-1]]  # each stream at RATE_HZ between two offline runs too
        for i in range(args.live_runs):
            with OccVOClient(svc.endpoint, f"{name}-live-{i}") as client:  # a new stream: nothing is a resend
                run = replay(client, frames, rate_hz=RATE_HZ, window=len(frames))
                arrived = client.arrived
                run["latency_ms"] = [(arrived[s] - t) * 1000.0 for s, t in enumerate(run["sent_at"]) if s in arrived]
                live.append(run)
            _quiet(procs)
            live_offs.append(offline(frames))
        paced = offline(frames, rate_hz=RATE_HZ)  # the odometry at the same rate: its steps start from idle cores
    reg = stats["registration"].stages
    return {
        "fast": fast,
        "offline": offs,
        "cpu_ms": cpu,
        "after_pose": {k: reg[k].p50_ms for k in AFTER_POSE_STAGES if k in reg},
        "worker_stats_p50": {role: {k: s.p50_ms for k, s in h.stages.items()} for role, h in stats.items() if h.stages},
        "live": live,
        "live_offline": live_offs,
        "paced": paced,
        "tile_query_ms": tile_ms,
    }


def _cpu_s(proc: psutil.Process) -> float:
    """User + system CPU seconds of a process so far."""
    return sum(proc.cpu_times()[:2])


def _quiet(procs: dict, timeout_s: float = 5.0) -> None:
    """Wait until the service processes use under 2% of a core over 200 ms (at most timeout_s)."""
    workers = [p for r, p in procs.items() if r != "router + client"]
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        cpu0 = sum(map(_cpu_s, workers))
        time.sleep(0.2)
        if sum(map(_cpu_s, workers)) - cpu0 < 0.004:
            return


def run_scene(scene_dir: Path, args) -> dict:
    scene = OccVOReleaseScene(scene_dir)
    frames = [scene[i] for i in range(len(scene))]
    offline(frames[:3])  # compile / warm caches
    with tempfile.TemporaryDirectory(prefix="occvo-pipeline-") as tmp:
        s = service(scene.name, frames, Path(tmp), args)
    offs, fast, live = s["offline"], s["fast"], s["live"]
    # each replay against the mean of the offline runs just before and just after it
    ratios = [f["fps"] / ((a["fps"] + b["fps"]) / 2) for f, a, b in zip(fast, offs, offs[1:])]
    steps = np.concatenate([o["step_ms"] for o in offs])
    step_med, step_p99 = float(np.median(steps)), float(np.percentile(steps, 99))
    lat = np.concatenate([r["latency_ms"] for r in live])
    lat_p50, lat_p99 = float(np.percentile(lat, 50)), float(np.percentile(lat, 99))
    identical = all(f["poses"] == len(frames) and np.array_equal(f["trajectory"], offs[0]["poses"]) for f in fast)
    identical &= all(np.array_equal(o["poses"], offs[0]["poses"]) for o in offs)
    offline_cpu = float(np.median([o["cpu_ms"] for o in offs]))
    service_cpu = s["cpu_ms"]
    added_cpu = (
        sum(service_cpu.values()) - service_cpu["registration"] + max(0.0, service_cpu["registration"] - offline_cpu)
    )
    p50_margins, p99_ratios = [], []  # each stream at RATE_HZ against the steps of the offline runs beside it
    for r, a, b in zip(live, s["live_offline"], s["live_offline"][1:]):
        near = np.concatenate([a["step_ms"], b["step_ms"]])
        p50_margins.append(np.percentile(r["latency_ms"], 50) - np.median(near))
        p99_ratios.append(np.percentile(r["latency_ms"], 99) / np.percentile(near, 99))
    ratio, p50_margin, p99_ratio = (float(np.median(v)) for v in (ratios, p50_margins, p99_ratios))
    service_stages = _medians_of([_stage_medians(f["pose_msgs"]) for f in fast])
    service_stages |= s["after_pose"]
    service_stages |= {k: v for k, v in s["worker_stats_p50"]["registration"].items() if k.startswith("complete.")}
    return {
        "frames": len(frames),
        "repeats": len(fast),
        "offline_fps": float(np.median([o["fps"] for o in offs])),
        "service_fps": float(np.median([f["fps"] for f in fast])),
        "ratio": ratio,
        "ratios": ratios,
        "latency_p50_over_offline_median_ms": p50_margin,
        "latency_p99_over_offline_p99": p99_ratio,
        "latency_p50_margins_ms": p50_margins,
        "offline_at_rate_median_ms": float(np.median(s["paced"]["step_ms"])),
        "latency_p50_over_offline_at_rate_ms": lat_p50 - float(np.median(s["paced"]["step_ms"])),
        "offline_registration_median_ms": step_med,
        "offline_registration_p99_ms": step_p99,
        "latency_p50_ms": lat_p50,
        "latency_p99_ms": lat_p99,
        "latency_rate_hz": RATE_HZ,
        "latency_poses": len(lat),
        "poses_identical": bool(identical),
        "errors": int(sum(f["errors"] for f in fast + live)),
        "goals": {
            "ratio >= 0.9": ratio >= 0.9,
            "latency p50 <= offline median + 10 ms": p50_margin <= 10.0,
            "latency p99 <= 1.5 x offline p99": p99_ratio <= 1.5,
            "CPU the service adds a frame <= 6 ms": added_cpu <= 6.0,
        },
        "offline_stage_median_ms": _medians_of([o["stages"] for o in offs]),
        "offline_cpu_ms": offline_cpu,
        "service_cpu_ms": service_cpu,
        "service_added_cpu_ms": added_cpu,
        "ratio_bound": offline_cpu / (offline_cpu + added_cpu),
        "service_stage_median_ms": service_stages,
        "worker_stats_p50_ms": s["worker_stats_p50"],
        "latency_stage_median_ms": _medians_of([_stage_medians(r["pose_msgs"]) for r in live]),
        "tile_query_p50_ms": float(np.percentile(s["tile_query_ms"], 50)),
        "tile_query_p99_ms": float(np.percentile(s["tile_query_ms"], 99)),
        "runs": {
            "offline_fps": [o["fps"] for o in offs],
            "service_fps": [f["fps"] for f in fast],
            "latency_ms": [r["latency_ms"] for r in live],
        },
    }


def _medians_of(dicts: list[dict[str, float]]) -> dict[str, float]:
    """Key -> the median of its values over the dicts (those that have it)."""
    return {k: float(np.median([d[k] for d in dicts if k in d])) for k in dicts[0]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["scene-0101", "scene-0268"])
    ap.add_argument("--repeats", type=int, default=10, help="lossless replays a scene, each between two offline runs")
    ap.add_argument("--live-runs", type=int, default=3, help="streams a scene at 2 Hz for the pose latency")
    ap.add_argument("--window", type=int, default=4)
    ap.add_argument("--hop-messages", type=int, default=300, help="0: no hop latency measurement")
    ap.add_argument("--output")
    ap.add_argument(
        "--registration-args", default="", help='extra flags of the registration worker, e.g. "--after-pose-nice 0"'
    )
    args = ap.parse_args(argv)
    if args.live_runs < 1 or args.repeats < 1:
        ap.error("--repeats and --live-runs must be at least 1: the ratio needs a replay, the 2 Hz latency a stream")

    results = {"hop": {}, "scenes": {}}
    for name in ("points", "axes", "voxels") if args.hop_messages > 0 else ():
        runs = [hop_latency(args.hop_messages, encoding=name) for _ in range(3)]
        size = runs[0][1]
        runs = [r for r, _ in runs]
        p50 = float(np.median([np.percentile(r, 50) for r in runs]))
        p99 = float(np.median([np.percentile(r, 99) for r in runs]))
        results["hop"][name] = {"p50_ms": p50, "p99_ms": p99, "bytes": size}
        print(f"hop 30k voxels {name:16s} {size / 1e6:5.2f} MB  p50 {p50:6.2f} ms  p99 {p99:6.2f} ms", flush=True)

    for name in args.scenes:
        d = SAMPLE / "occupancy" / name
        if not d.is_dir():
            print(f"{name}: not found at {d}, skipped")
            continue
        results["scenes"][name] = r = run_scene(d, args)
        print_scene(name, r)
    if args.output:
        Path(args.output).write_text(json.dumps(results, indent=2, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
