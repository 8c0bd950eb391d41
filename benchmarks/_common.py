"""What the benchmarks share: where the sample data is, the real scenes' command line, a busy neighbour, percentiles
and the printing of a report.

The scripts run as `python benchmarks/NAME.py` with occvo installed (`pip install -e .`): Python puts this folder first
on the module path, so `import _common` (and a script's own `_NAME_*.py` parts) load from here without any path edits.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SAMPLE = REPO.parent / "shared" / "data" / "occvo-sample"  # the real scenes, beside the checkout (tests/conftest.py)
REAL_SCENES = ["scene-0101", "scene-0268"]


# ---------------------------------------------------------------- statistics


def pct(a, q) -> float | None:
    """The q-th percentile of the finite values of a, None when there are none."""
    a = np.asarray([x for x in a if x == x], float)
    return float(np.percentile(a, q)) if len(a) else None


def slope_per_min(t, y) -> float | None:
    """Least-squares slope of y per minute of t (seconds)."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    return float(np.polyfit(t / 60.0, y, 1)[0]) if len(t) >= 3 and np.ptp(t) > 0 else None


def stage_medians(timings: list[dict[str, float]]) -> dict[str, float]:
    """Median ms of each stage over some poses' timings_ms, largest first (where the slowest frames' time went)."""
    names = {k for t in timings for k in t}
    med = {k: float(np.median([t.get(k, 0.0) for t in timings])) for k in names}
    return dict(sorted(med.items(), key=lambda kv: -kv[1]))


def step_ms(frames, threads: int = 1) -> np.ndarray:
    """ms of each OccVO.step over the frames, in order, on a new OccVO with `threads` kernel threads."""
    from occvo_core import OccVO

    vo, ts = OccVO(threads=threads), []
    for f in frames:
        t0 = time.perf_counter()
        vo.step(f)
        ts.append((time.perf_counter() - t0) * 1000.0)
    return np.array(ts)


# ---------------------------------------------------------------- printing


def _text(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, list) and v and all(isinstance(x, list) for x in v):  # samples by run: their sizes
        return "; ".join(_text(x) for x in v)
    if isinstance(v, list) and len(v) > 12 and all(isinstance(x, (int, float)) for x in v):
        return f"{len(v)} values, median {_text(float(np.median(v)))}"
    if isinstance(v, list) and all(isinstance(x, (int, float)) for x in v):
        return ", ".join(_text(x) for x in v)
    return json.dumps(v, default=float) if isinstance(v, (dict, list)) else str(v)


def _lines(r: dict, depth: int):
    pad = "  " * depth
    for k, v in r.items():
        if isinstance(v, dict) and v and all(not isinstance(x, (dict, list)) for x in v.values()) and len(v) <= 12:
            yield f"{pad}{k}: " + ", ".join(f"{a} {_text(b)}" for a, b in v.items())
        elif isinstance(v, dict):
            yield f"{pad}{k}:"
            yield from _lines(v, depth + 1)
        elif isinstance(v, list) and v and all(isinstance(x, dict) for x in v):  # rows: a table
            cols = list(dict.fromkeys(c for row in v for c in row))
            yield f"{pad}{k}:"
            yield pad + "  " + "  ".join(f"{c:>10}" for c in cols)
            for row in v:
                yield pad + "  " + "  ".join(f"{_text(row.get(c, '-')):>10}" for c in cols)
        else:
            yield f"{pad}{k}: {_text(v)}"


def print_scene(name: str, r: dict) -> None:
    """One scene's (or run's) report, readable: a line a figure, nested sections indented, lists of rows as tables."""
    print(f"{name}:")
    for line in _lines(r, 1):
        print(line)
    sys.stdout.flush()


# ---------------------------------------------------------------- the real scenes


def measure_scenes(argv, description: str, measure_one) -> dict | None:
    """{scene: measure_one(sample, scene, config)} for the --sample, --scenes and --config of a benchmark on the real
    scenes; None, after saying so, without the sample."""
    from occvo_core import OccVOConfig

    ap = argparse.ArgumentParser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sample", type=Path, default=SAMPLE)
    ap.add_argument("--scenes", nargs="+", default=REAL_SCENES)
    ap.add_argument("--config", type=Path, help="odometry config (JSON5), e.g. {gicp: {source_pick: 'balanced'}}")
    args = ap.parse_args(argv)
    if not (args.sample / "occupancy").is_dir():
        print(f"no sample data at {args.sample}", file=sys.stderr)
        return None
    config = OccVOConfig.load(args.config) if args.config else OccVOConfig()
    return {name: measure_one(args.sample, name, config) for name in args.scenes}


def benchmark_main(argv, description: str, measure_one) -> int:
    """A real-scene benchmark's main: measure_scenes, print_scene for each, then the report as one JSON line."""
    report = measure_scenes(argv, description, measure_one)
    if report is None:
        return 2
    for name, r in report.items():
        print_scene(name, r)
    print(json.dumps(report))
    return 0


def shifted(gt: np.ndarray, frames: float) -> np.ndarray:
    """Ground-truth positions `frames` keyframes later (linear between keyframes, extrapolated past the ends)."""
    out = gt.copy()
    n = len(gt)
    for t in range(n):
        a = t + frames
        i = int(np.clip(np.floor(a), 0, n - 2))
        out[t, :3, 3] = gt[i, :3, 3] + (a - i) * (gt[i + 1, :3, 3] - gt[i, :3, 3])
    return out


# a release scene run four ways: forward, reversed in time, turned 180 degrees about z (the ego drives backwards),
# both; with the signs each way gives the data's time offset d, a lead fixed in the ego frame e, a lead along the
# travel l and the residual (time_offset.py)
RUNS = {
    "forward": (1, 1, 1, 1),
    "reversed": (-1, -1, 1, 1),
    "turned": (1, -1, 1, -1),  # signs of d, e, l, residual
    "turned+rev": (-1, 1, 1, -1),
}


def four_ways(root: Path, name: str) -> dict[str, tuple[list, np.ndarray]]:
    """{run: (frames, ground truth)} of a release scene in RUNS' four ways."""
    from occvo_core.datasets import OccVOReleaseScene
    from occvo_core.frame import OccupancyFrame

    source = OccVOReleaseScene(root / "occupancy" / name)
    frames = [source[i] for i in range(len(source))]
    gt = np.asarray(source.gt_poses)
    gt = np.linalg.inv(gt[0]) @ gt
    turn = np.diag([-1.0, -1.0, 1.0, 1.0])
    turned = [OccupancyFrame(f.points * [-1.0, -1.0, 1.0], f.labels, f.index) for f in frames]
    turned_gt = turn @ gt @ turn  # the turned ego's poses
    return {
        "forward": (frames, gt),
        "reversed": (frames[::-1], gt[::-1]),
        "turned": (turned, turned_gt),
        "turned+rev": (turned[::-1], turned_gt[::-1]),
    }


# ---------------------------------------------------------------- a busy machine, memory


def vm_hwm_mb(pid: int) -> float:
    """Peak resident set of a process so far (Linux /proc VmHWM), MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def _neighbour(duty: float) -> None:
    """A noisy neighbour on one core: busy `duty` of every 100 ms (--neighbour-load; a stand-in for host steal)."""
    while True:
        t = time.perf_counter()
        while time.perf_counter() - t < duty * 0.1:
            pass
        time.sleep((1.0 - duty) * 0.1)


def start_neighbours(duty: float) -> list:
    """One noisy neighbour process a core (daemons; terminate() them when done). None for duty 0."""
    if duty <= 0:
        return []
    ctx = multiprocessing.get_context("spawn")
    neighbours = [ctx.Process(target=_neighbour, args=(duty,), daemon=True) for _ in range(os.cpu_count() or 1)]
    for proc in neighbours:
        proc.start()
    return neighbours
