"""Time to generate a default synthetic scene (40 frames at 2 Hz, default noise, traffic): construction plus
every frame (rendering, camera visibility pass, noise). Prints the median over repeats and the ratio to the
5 s budget. The first run compiles or loads the numba kernels and is reported apart.

    python benchmarks/sim_generation.py [--repeats 5] [--frames 40] [--seed 0]
"""

from __future__ import annotations

import argparse
import statistics
import time


def generate(seed: int, frames: int) -> float:
    from occvo_core.sim import SyntheticScene

    t = time.perf_counter()
    scene = SyntheticScene(seed=seed, frames=frames)
    for i in range(len(scene)):
        scene[i]
    return time.perf_counter() - t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    t0 = time.perf_counter()
    from occvo_core.sim import SyntheticScene  # noqa: F401

    SyntheticScene(seed=args.seed, frames=1)[0]
    print(f"first use (imports, numba kernels): {time.perf_counter() - t0:.2f} s")
    times = []
    for r in range(args.repeats):
        times.append(generate(args.seed + r, args.frames))
        print(f"  seed {args.seed + r}: {times[-1]:.2f} s")
    med = statistics.median(times)
    print(
        f"median {med:.2f} s for {args.frames} frames ({1000 * med / args.frames:.0f} ms/frame); "
        f"ratio to the 5 s budget: {med / 5.0:.2f}"
    )


if __name__ == "__main__":
    main()
