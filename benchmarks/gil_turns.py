"""A frame's registration beside a thread running Python, at several interpreter switch intervals.

A registration takes the interpreter lock back after every compiled kernel; while another thread runs Python (a
stream's map tiles, a decode) each take waits until that thread is asked to give the lock up, after the switch
interval. The workers set it short (services/os_tuning.short_gil_turns); this shows why, and what it costs two
threads that both run Python.

    python benchmarks/gil_turns.py [--scene scene-0101] [--intervals-ms 5 0.5 0.1] [--rounds 2]

Prints, per interval and round, `OccVO.step` p50 / p90 (one kernel thread, the first frame left out) alone and beside
a thread looping in Python, and the wall time of two threads each counting to 10 million in Python.
"""

from __future__ import annotations

import argparse
import sys
import threading
import time

import numpy as np
from _common import SAMPLE, step_ms

from occvo_core.datasets import OccVOReleaseScene


def steps_ms(frames) -> tuple[float, float]:
    """p50, p90 of OccVO.step over the frames after the first, one kernel thread."""
    ts = step_ms(frames)[1:]
    return float(np.median(ts)), float(np.percentile(ts, 90))


def beside_python(frames) -> tuple[float, float]:
    """steps_ms beside a thread that runs Python the whole time."""
    stop = threading.Event()

    def busy():
        while not stop.is_set():
            sum(range(1000))

    thread = threading.Thread(target=busy)
    thread.start()
    try:
        return steps_ms(frames)
    finally:
        stop.set()
        thread.join()


def two_python_threads_s(n: int = 10_000_000) -> float:
    """Wall seconds for two threads each counting to n in Python (what a short interval costs them)."""

    def count():
        x = 0
        for k in range(n):
            x += k

    threads = [threading.Thread(target=count) for _ in range(2)]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return time.perf_counter() - t0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="scene-0101")
    ap.add_argument("--intervals-ms", type=float, nargs="+", default=[5.0, 0.5, 0.1])
    ap.add_argument("--rounds", type=int, default=2, help="the intervals alternated this many times")
    args = ap.parse_args()
    path = SAMPLE / "occupancy" / args.scene
    if not path.is_dir():
        ap.error(f"no scene at {path}: the sample data lies beside the checkout (../shared)")
    scene = OccVOReleaseScene(path)
    frames = [scene[i] for i in range(len(scene))]
    steps_ms(frames[:3])  # compiles
    before = sys.getswitchinterval()
    try:
        for r in range(args.rounds):
            for ms in args.intervals_ms:
                sys.setswitchinterval(ms / 1000.0)
                (a50, a90), (b50, b90) = steps_ms(frames), beside_python(frames)
                print(
                    f"round {r + 1}  switch {ms:4.1f} ms  step p50/p90 alone {a50:6.1f} / {a90:6.1f} ms, beside a "
                    f"Python thread {b50:6.1f} / {b90:6.1f} ms; two Python threads {two_python_threads_s():.2f} s"
                )
    finally:
        sys.setswitchinterval(before)
    return 0


if __name__ == "__main__":
    sys.exit(main())
