"""Long loop drive through the service with flat memory: a synthetic drive lapping a block circuit
(SyntheticScene route="loop"), replayed losslessly (window 4) through router + inference + registration + map
workers as separate processes, the registration worker's RSS sampled every second.

    python benchmarks/long_drive.py [--frames 3600] [--seed 0] [--blocks 4x4] [--radius 150]
    python benchmarks/long_drive.py --frames 300 --blocks 2x2          # a short run for development

Reports: frames, wall time; registration-worker RSS median / peak of the first half vs the last half of the drive
and their ratio (goal: last-half peak <= 1.1 x first-half peak), VmHWM at the half and at the end; map voxels
served; APE RMSE of the whole trajectory against the scene's gt_poses (occvo_core.eval); and the revisited start:
the map tiles around the start (20 m tiles, [-20, 20) m in x and y of the odometry frame, which is the first
pose's) queried at the last frame of lap 1 before the ego comes back near its start, against the same query at
the same point of the last full lap (after every revisit): precision and completion (occvo_core.map_metrics,
0.4 m, static classes) in the cells lap 1's cameras saw (goal precision >= 0.9: where lap 1 built a map to match)
and over the whole start area, and of the last lap's start voxels farther than 0.4 m from lap 1's, the share on
the true static map (structure lap 1 did not see, against misplaced voxels). Eviction (--radius with
a durable store) is used when the registration worker has --store-path; otherwise the run says "eviction: off".
Prints a table, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import pickle
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import psutil

warnings.filterwarnings("ignore", category=RuntimeWarning)

from _common import vm_hwm_mb  # noqa: E402
from _drive_truth import START_TILES  # noqa: E402
from _long_drive_report import analyse, generate_only  # noqa: E402

from occvo_core.sim import SyntheticScene  # noqa: E402
from occvo_services.client import OccVOClient, ServiceError  # noqa: E402
from occvo_services.commands.replay import replay  # noqa: E402
from occvo_services.local import REPO, LocalService  # noqa: E402


def worker_has_store() -> bool:
    out = subprocess.run(
        [sys.executable, "-m", "occvo_services.registration_worker", "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    return "--store-path" in out.stdout and "--working-radius-m" in out.stdout


def snapshot_frames(scene: SyntheticScene, away_m: float = 80.0) -> tuple[list[int], float]:
    """For each full lap, its last frame at which the ego is still at least `away_m` (or 80 % of the lap's
    farthest distance) from its start, i.e. just before it comes back there; and that distance in lap 1."""
    if len(scene.lap_starts) < 3:
        raise SystemExit(
            f"the drive must do at least 2 full laps, this one does {len(scene.lap_starts) - 1} "
            f"(laps start at frames {scene.lap_starts.tolist()}): more --frames or smaller --blocks"
        )
    xy = scene.gt_poses[:, :2, 3]
    d = np.linalg.norm(xy - xy[0], axis=1)

    def last_far(a: int, b: int) -> int:
        thr = min(away_m, 0.8 * d[a:b].max())
        return a + int(np.nonzero(d[a:b] >= thr)[0][-1])

    ks = [last_far(a, b) for a, b in zip(scene.lap_starts[:-1], scene.lap_starts[1:])]
    return ks, float(d[ks[0]])


class Budget(Exception):
    """The time budget ran out: the drive stops at the frame in hand."""


class RssSampler(threading.Thread):
    """RSS of one process every `period` s, with how many poses had come back by then."""

    def __init__(self, pid: int, done, period: float = 1.0):
        super().__init__(daemon=True)
        self.proc, self.done, self.period = psutil.Process(pid), done, period
        self.samples: list[tuple[float, int, float]] = []  # (t, frames done, rss MB)
        self.halt = threading.Event()

    def run(self) -> None:
        t0 = time.perf_counter()
        while not self.halt.is_set():
            try:
                rss = self.proc.memory_info().rss / 2**20
            except psutil.Error:
                return
            self.samples.append((time.perf_counter() - t0, self.done(), rss))
            self.halt.wait(self.period)


def start_map(client: OccVOClient, seq: int, timeout: float = 120.0) -> tuple[np.ndarray, np.ndarray]:
    """The service's map around the start once frame `seq` is registered and its map update applied."""
    client.wait_pose(seq, timeout)
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        try:
            info = client.map_info()
            if info.last_seq is not None and info.last_seq >= seq:
                break
        except ServiceError:
            pass
        time.sleep(0.05)
    try:
        tiles = client.region(**START_TILES)
    except ServiceError:
        tiles = []
    if not tiles:
        return np.zeros((0, 3)), np.zeros(0, np.uint8)
    return (np.concatenate([t.points.to_numpy() for t in tiles]), np.concatenate([t.labels.to_numpy() for t in tiles]))


def run(args, scene: SyntheticScene) -> dict:
    """Replay the drive through the service; returns the raw measurements (pickled by main before analysis)."""
    laps, away = snapshot_frames(scene)
    n = len(scene)
    eviction = (not args.no_store) and worker_has_store()
    with tempfile.TemporaryDirectory(prefix="occvo-long-") as tmp:
        log_dir = Path(args.log_dir or tmp)
        log_dir.mkdir(parents=True, exist_ok=True)
        reg_args = (
            ["--store-path", str(Path(tmp) / "occvo.db"), "--working-radius-m", str(args.radius)] if eviction else []
        )
        if args.after_pose_nice is not None:
            reg_args += ["--after-pose-nice", str(args.after_pose_nice)]
        svc = LocalService(
            worker_args={"registration": reg_args}, common_args=["--log-level", "WARNING"], log_dir=log_dir
        )
        svc.start()
        try:
            with OccVOClient(svc.endpoint, stream="loop") as client:
                client.wait_for_workers(timeout=60)
                pid = svc.procs["registration"].pid
                sampler = RssSampler(pid, lambda: len(client.poses))
                snaps, marks = {}, {}
                t_run = time.perf_counter()

                def progress(i: int, total: int) -> None:
                    if i in laps:
                        snaps[laps.index(i) + 1] = (i, *start_map(client, i, args.timeout))
                    if args.budget_s and time.perf_counter() - t_run > args.budget_s:
                        raise Budget(i)
                    if i == total // 2:
                        client.wait_pose(i, args.timeout)
                        marks["hwm_half"] = vm_hwm_mb(pid)
                        marks["voxels_half"] = client.map_info().voxel_count
                    if i % 300 == 0:
                        print(
                            f"  frame {i}/{total}  {time.perf_counter() - t_run:.0f} s  registration rss "
                            f"{psutil.Process(pid).memory_info().rss / 2**20:.0f} MB  hwm {vm_hwm_mb(pid):.0f} MB",
                            flush=True,
                        )

                sampler.start()
                try:
                    out = replay(client, scene, window=args.window, timeout=args.timeout, progress=progress)
                except Budget as stop:  # keep what was sent: wait for it, then report on those frames
                    sent = int(stop.args[0]) + 1
                    client.wait_pose(sent - 1, args.timeout)
                    poses = dict(client.poses)
                    out = {
                        "frames": sent,
                        "poses": len(poses),
                        "errors": len(client.errors),
                        "seconds": time.perf_counter() - t_run,
                        "trajectory": np.array([poses[q].matrix() for q in sorted(poses)]),
                        "budget_stop": True,
                    }
                    out["fps"] = out["poses"] / out["seconds"]
                    print(
                        f"  time budget of {args.budget_s:g} s reached: the drive stops after {sent} frames", flush=True
                    )
                finally:
                    sampler.halt.set()
                    sampler.join()
                hwm_end = vm_hwm_mb(pid)
                info_end = client.map_info()
                reg = {h.role: h for h in client.stats()}.get("registration")
                n_done = out["frames"]
                snaps["end"] = (n_done - 1, *start_map(client, n_done - 1, args.timeout))
        finally:
            codes = svc.stop()
        if out["poses"] != out["frames"]:
            for p in sorted(log_dir.glob("*.log")):
                print(p.name, p.read_text()[-2000:], file=sys.stderr)
    return {
        "n": n_done,
        "n_planned": n,
        "eviction": eviction,
        "snapshot_frames": laps,
        "away_m": away,
        "out": {k: v for k, v in out.items() if k != "pose_msgs"},
        "samples": sampler.samples,
        "snaps": snaps,
        "marks": marks,
        "hwm_end": hwm_end,
        "voxels_end": info_end.voxel_count,
        "tiles_end": info_end.tile_count,
        "registration_counters": dict(reg.counters) if reg else {},
        "registration_stages_ms": {k: v.mean_ms for k, v in reg.stages.items()} if reg else {},
        "exit_codes": codes,
        "bench_rss_mb": psutil.Process().memory_info().rss / 2**20,
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--blocks", default="4x4", help="loop around NXxNY city blocks (4x4: ~1.1 km a lap)")
    ap.add_argument("--radius", type=float, default=120.0, help="registration working radius, m (with a store)")
    ap.add_argument("--window", type=int, default=4)
    ap.add_argument(
        "--after-pose-nice",
        type=int,
        help="niceness of the registration worker's work after a pose "
        "(default: the worker's, 10; 0: the lanes', faster for one stream replayed as fast as it goes)",
    )
    ap.add_argument("--no-store", action="store_true", help="run without the durable store and eviction")
    ap.add_argument("--timeout", type=float, default=300.0, help="s without a pose before the replay gives up")
    ap.add_argument("--log-dir", help="keep the workers' logs here (default: a temporary folder)")
    ap.add_argument("--budget-s", type=float, default=0.0, help="stop the drive after this many seconds (0: none)")
    ap.add_argument("--raw", help="pickle the raw measurements here (default: a temporary file)")
    ap.add_argument("--analyse", metavar="RAW", help="only analyse a pickle written by an earlier run (same flags)")
    ap.add_argument(
        "--generate-only", action="store_true", help="only time the scene's frames and this process's memory"
    )
    args = ap.parse_args()
    blocks = tuple(int(v) for v in args.blocks.lower().split("x"))
    t_build = time.perf_counter()
    scene = SyntheticScene(seed=args.seed, frames=args.frames, route="loop", loop_blocks=blocks)
    t_build = time.perf_counter() - t_build
    if args.generate_only:
        print(json.dumps(generate_only(scene, t_build)))
        return 0
    if args.analyse:
        raw = pickle.loads(Path(args.analyse).read_bytes())
    else:
        raw = run(args, scene)
        path = Path(args.raw or tempfile.mkstemp(prefix="occvo-long-", suffix=".pkl")[1])
        path.write_bytes(pickle.dumps(raw))
        print(f"raw measurements: {path}")
    res = analyse(raw, scene, args, t_build)
    print(json.dumps(res))
    return 0 if res["poses"] == res["frames"] else 1


if __name__ == "__main__":
    sys.exit(main())
