"""Does `occvo run --ros2-bag` grow linearly with the drive? Bytes per frame of a short and a long synthetic drive's
bag (seed 0, default noise, 2 Hz), and their ratio (goal: the long drive's within 1.2x of the short one's: the path is
a window of 100 poses and the map is logged near the ego, the whole of each once at the end).

    python benchmarks/bag_size.py [--frames 40 3600] [--seed 0] [--threads 1]   # the long drive takes a while

`occvo run`'s own memory grows with a synthetic drive (2.0 GB at 600 frames, bag or not): 3,600 frames need a machine
with well over 20 GB; `--frames 40 400` runs anywhere (docs/ros2.md has both figures).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import tempfile
import time
from pathlib import Path

from occvo_cli.cli import main as occvo


def bag_bytes(frames: int, seed: int, threads: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        bag, start = Path(tmp) / "bag", time.perf_counter()
        argv = ["run", "--quiet", "--frames", str(frames), "--seed", str(seed), "--threads", str(threads)]
        with contextlib.redirect_stdout(io.StringIO()):  # the run's own summary: only the report on stdout
            code = occvo([*argv, "--out", str(Path(tmp) / "out"), "--ros2-bag", str(bag)])
        if code != 0:
            raise SystemExit(f"occvo run --frames {frames} failed")
        size = sum(f.stat().st_size for f in bag.iterdir())
        return {
            "frames": frames,
            "bytes": size,
            "bytes_per_frame": size / frames,
            "seconds": time.perf_counter() - start,
        }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, nargs=2, default=[40, 3600])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    short, long = (bag_bytes(n, args.seed, args.threads) for n in args.frames)
    ratio = long["bytes_per_frame"] / short["bytes_per_frame"]
    print(json.dumps({"short": short, "long": long, "ratio": ratio, "linear": ratio <= 1.2}, indent=2, default=float))


if __name__ == "__main__":
    main()
