"""Registration speed: median ms per frame for each stage and in total, over repeated runs of real scenes.

    python benchmarks/registration.py [--repeats 3] [--scenes scene-0101 scene-0268] [--threads 1 0] [--config C.json5]
        [--neighbour-load 0.5] [--stage-clock cpu] [--json out.json]

Prints one table a scene (wall-clock medians, and CPU-time medians, which a busy machine disturbs less) and the
ratio to the 40 ms/frame goal. --stage-clock cpu times the stages in the calling thread's CPU time instead of wall
time: on a busy host the stage figures then move little with the load (at --threads 1 a stage's whole CPU time;
at more threads only the calling thread's share). The first frame only seeds the map and is left out; the first run compiles.
--neighbour-load D runs it all beside a busy neighbour: one process a core, busy D of every 100 ms (streams_load.py's),
so the kernels' threads find their cores taken part of the time, as on a shared host."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from _common import SAMPLE, start_neighbours

from occvo_core import OccVO, OccVOConfig
from occvo_core.datasets import OccVOReleaseScene
from occvo_core.eval import ape_rmse
from occvo_core.odometry import Stopwatch

GOAL_MS = 40.0


def run_once(frames, config, threads=0):
    vo = OccVO(config, threads=threads)
    wall, cpu, stages = [], [], {}
    for frame in frames:
        w0, c0 = time.perf_counter(), time.process_time()
        result = vo.step(frame)
        w1, c1 = time.perf_counter(), time.process_time()
        if result.status != "ok":
            continue
        wall.append((w1 - w0) * 1e3)
        cpu.append((c1 - c0) * 1e3)
        for stage, ms in result.timings_ms.items():
            stages.setdefault(stage, []).append(ms)
    return vo, wall, cpu, stages


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sample", type=Path, default=SAMPLE)
    ap.add_argument("--scenes", nargs="+", default=["scene-0101", "scene-0268"])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--threads",
        type=int,
        nargs="+",
        default=[0],
        help="kernel thread counts to measure, 0 = all cores (e.g. --threads 1 0: one core, then all)",
    )
    ap.add_argument("--json", type=Path)
    ap.add_argument(
        "--motion-search", action="store_true", help="with the semantic BEV motion search (as --from-images)"
    )
    ap.add_argument("--config", type=Path, help="an OccVOConfig JSON5 file (default: the built-in defaults)")
    ap.add_argument(
        "--neighbour-load", type=float, default=0.0, help="a neighbour process a core busy this share of the time"
    )
    ap.add_argument(
        "--stage-clock",
        choices=["wall", "cpu"],
        default="wall",
        help="time stages in wall time or in the calling thread's CPU time (a busy host disturbs it less)",
    )
    args = ap.parse_args(argv)
    if args.stage_clock == "cpu":
        Stopwatch.clock = staticmethod(time.thread_time)
    if not (args.sample / "occupancy").is_dir():
        print(f"no sample data at {args.sample}", file=sys.stderr)
        return 2
    config = OccVOConfig.load(args.config) if args.config else OccVOConfig()
    if args.motion_search:
        config = config.with_motion_search()
    report = {}
    neighbours = start_neighbours(args.neighbour_load)
    try:
        measure(args, config, report)
    finally:
        for proc in neighbours:
            proc.terminate()
    print(json.dumps(report, indent=2))
    if args.json:
        args.json.write_text(json.dumps(report, indent=2) + "\n")
    return 0


def measure(args, config, report: dict) -> None:
    for name in args.scenes:
        source = OccVOReleaseScene(args.sample / "occupancy" / name)
        frames = [source[i] for i in range(len(source))]
        for threads in args.threads:
            key = name if len(args.threads) == 1 else f"{name} threads={threads}"
            run_once(frames[:3], config, threads)  # compile / warm caches
            walls, cpus, stage_runs, rmses = [], [], [], []
            for _ in range(args.repeats):
                vo, wall, cpu, stages = run_once(frames, config, threads)
                walls.append(np.median(wall))
                cpus.append(np.median(cpu))
                stage_runs.append({k: float(np.median(v)) for k, v in stages.items()})
                rmses.append(ape_rmse(source.gt_poses, vo.poses))
            stage_median = {k: float(np.median([r[k] for r in stage_runs])) for k in stage_runs[0]}
            total = float(np.median(walls))
            report[key] = {
                "frames": len(frames),
                "repeats": args.repeats,
                "threads": threads,
                "ms_per_frame_median": total,
                "cpu_ms_per_frame_median": float(np.median(cpus)),
                "ms_per_stage_median": stage_median,
                "ratio_to_goal": total / GOAL_MS,
                "ape_rmse_m": float(np.median(rmses)),
                "neighbour_load": args.neighbour_load,
                "stage_clock": args.stage_clock,
            }
            print(f"\n{key}: {len(frames)} frames, {args.repeats} runs (median of per-run medians)")
            print(f"  {'stage (' + args.stage_clock + ')':<24}{'ms':>9}")
            for stage, ms in stage_median.items():
                print(f"  {stage:<24}{ms:>9.1f}")
            print(f"  {'total (wall)':<24}{total:>9.1f}   goal {GOAL_MS:.0f} ms: ratio {total / GOAL_MS:.2f}")
            print(f"  {'total (cpu)':<24}{np.median(cpus):>9.1f}")
            print(f"  APE RMSE {np.median(rmses):.3f} m")


if __name__ == "__main__":
    sys.exit(main())
