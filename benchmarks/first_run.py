"""A first `occvo run` after install against a warm one: numba's cache empty (a fresh NUMBA_CACHE_DIR), then full.

    python benchmarks/first_run.py [--input SCENE_DIR] [--repeats 1]

Prints, per pair, each run's compile_s (kernel warm-up before the first frame) and ms_per_frame_median, and the
first run's median over the warm one's (goal: <= 1.5, the compile time reported apart). Run it on a quiet machine:
other jobs on the cores move both medians.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def occvo_run(args: list[str], cache: str, out: str) -> dict:
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    env = dict(os.environ, NUMBA_CACHE_DIR=cache, PYTHONPATH=path)
    proc = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "run", "--json", "--quiet", "--out", out, *args],
        capture_output=True,
        text=True,
        env=env,
        check=True,
    )
    return json.loads(proc.stdout)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--input", help="scene folder (default: the synthetic scene of `occvo run`)")
    p.add_argument("--repeats", type=int, default=1)
    args = p.parse_args()
    extra = ["--input", args.input] if args.input else []
    for _ in range(args.repeats):
        with tempfile.TemporaryDirectory() as cache, tempfile.TemporaryDirectory() as out:
            first, warm = (occvo_run(extra, cache, out) for _ in range(2))
        print(
            json.dumps(
                {
                    "first": {k: first[k] for k in ("compile_s", "ms_per_frame_median")},
                    "warm": {k: warm[k] for k in ("compile_s", "ms_per_frame_median")},
                    "first_over_warm": round(first["ms_per_frame_median"] / warm["ms_per_frame_median"], 2),
                }
            )
        )


if __name__ == "__main__":
    main()
