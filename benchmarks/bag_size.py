"""Does `occvo run --ros2-bag` grow linearly with the drive? Bytes per frame of a short and a long synthetic drive's
bag (seed 0, default noise, 2 Hz), and their ratio (goal: the long drive's within 1.2x of the short one's: the path is
a window of 100 poses and the map is logged near the ego, the whole of each once at the end).

    python benchmarks/bag_size.py [--frames 40 3600] [--route loop] [--seed 0] [--threads 1]   # a while

The frames go through OdometryPipeline into Ros2Bag as `occvo run --ros2-bag` sends them. `--route walk` (occvo
run's drive) grows the odometry's own memory with the drive (2.0 GB at 600 frames, bag or not): 3,600 frames of it
need well over 20 GB; `--route loop` (the default here: laps of a block circuit, benchmarks/long_drive.py's) keeps
it flat.
"""

from __future__ import annotations

import argparse
import json
import resource
import tempfile
import time
from pathlib import Path

from occvo_core import OccVOConfig
from occvo_core.pipeline import OdometryPipeline
from occvo_core.sim import SyntheticScene
from occvo_core.viz.ros2_bag import Ros2Bag


def bag_bytes(frames: int, seed: int, threads: int, route: str) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        path, start = Path(tmp) / "bag", time.perf_counter()
        scene = SyntheticScene(seed=seed, frames=frames, route=route)
        bag = Ros2Bag(path)
        pipeline = OdometryPipeline(scene, OccVOConfig(), threads=threads, progress=False).run(on_step=bag.step)
        bag.finish(pipeline.odometry)
        size = sum(f.stat().st_size for f in path.iterdir())
        return {
            "frames": frames,
            "bytes": size,
            "bytes_per_frame": size / frames,
            "seconds": time.perf_counter() - start,
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs=2, default=[40, 3600])
    ap.add_argument("--route", choices=("loop", "walk"), default="loop")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    short, long = (bag_bytes(n, args.seed, args.threads, args.route) for n in args.frames)
    ratio = long["bytes_per_frame"] / short["bytes_per_frame"]
    report = {"route": args.route, "short": short, "long": long, "ratio": ratio, "linear": ratio <= 1.2}
    print(json.dumps(report, indent=2, default=float))


if __name__ == "__main__":
    main()
