"""Accuracy on protocols that cannot overfit: real scenes four ways, synthetic seeds to choose and others to confirm.

    python benchmarks/accuracy.py [--sets dihedral real choose confirm] [--config A.json5 ...] [--output FILE]
                                  [--jobs 2]

real     every scene in ../shared/data/occvo-sample run four ways (benchmarks/time_offset.py's variants: forward,
         reversed, turned 180 degrees, both). From the four best time shifts of a scene: its data offset d and the
         lean e fixed in the ego frame (which a source selection that prefers a direction in the ego frame gives).
choose   synthetic seeds 0-19 (default noise): where settings are compared.
confirm  synthetic seeds 100-119: only to confirm a choice, never to make one.
dihedral every real scene and every confirming seed run eight ways: every frame turned about z by 0, 90, 180 and
         270 degrees (exact on the 0.4 m lattice), each forward and reversed in time; the ground truth turned with
         them (R G R^-1) and reversed (order and stamps). An odometry with no preferred direction turns its
         trajectory and changes nothing else: per scene (or seed) and time direction, the spread (max - min) of each
         figure over the four turns; per seed, the APE spread over all eight. Each variant's ground truth and
         estimate are written to a temporary directory as TUM files and scored by `occvo eval --fit-time-offset`.
Per run: plain APE (the paper's metric), time-fitted APE (occvo_core.time_fit), path-length ratio (estimate over
truth), best time shift; synthetic runs also map precision and completion. Per set: mean, worst, success ratio.
Several --config files (JSON5 OccVOConfig overrides; "default" for the built-in one) are run side by side.
Synthetic frames are rendered once into --cache (default /tmp/occvo-accuracy-cache) and reused.
Prints a table and writes JSON to --output. Runs in occvo_core.reproducible's pinned floating-point environment, so
the figures are the same on every x86-64 machine with AVX2.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from _common import RUNS, SAMPLE, four_ways

from occvo_core import OccVO, OccVOConfig
from occvo_core.eval import ape_rmse, success
from occvo_core.frame import OccupancyFrame
from occvo_core.reproducible import is_pinned, restart_pinned
from occvo_core.time_fit import fit_time_offset
from occvo_core.trajectory_stats import path_length

SETS = {"choose": range(0, 20), "confirm": range(100, 120)}
TURNS = (0, 90, 180, 270)  # degrees about z
DIRECTIONS = ("forward", "reversed")


def load_config(spec: str) -> OccVOConfig:
    return OccVOConfig() if spec == "default" else OccVOConfig.load(spec)


def synthetic(seed: int, cache: Path) -> tuple[list, np.ndarray, tuple]:
    """Frames, ground truth and true static map of a seed, rendered once."""
    path = cache / f"seed{seed}.npz"
    if not path.exists():
        from occvo_core.sim import SyntheticScene

        scene = SyntheticScene(seed=seed)
        frames = [scene[i] for i in range(len(scene))]
        points, labels = scene.static_map()
        sizes = np.array([len(f.labels) for f in frames])
        cache.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")  # two processes may render one seed at once
        np.savez(
            tmp,
            sizes=sizes,
            points=np.concatenate([f.points for f in frames]),
            labels=np.concatenate([f.labels for f in frames]),
            gt=scene.gt_poses,
            map_points=points,
            map_labels=labels,
        )
        os.replace(tmp, path)
    z = np.load(path)
    cut = np.cumsum(z["sizes"])[:-1]
    frames = [
        OccupancyFrame(p, lab, i, i / 2.0)
        for i, (p, lab) in enumerate(zip(np.split(z["points"], cut), np.split(z["labels"], cut)))
    ]
    return frames, z["gt"], (z["map_points"], z["map_labels"])


def turn_matrix(degrees: int) -> np.ndarray:
    """4x4 turn about z by a multiple of 90 degrees, exact (entries 0 and +-1)."""
    c, s = {0: (1, 0), 90: (0, 1), 180: (-1, 0), 270: (0, -1)}[degrees]
    out = np.eye(4)
    out[:2, :2] = [[c, -s], [s, c]]
    return out


def variant(frames: list, gt: np.ndarray, degrees: int, direction: str) -> tuple[list, np.ndarray]:
    """The drive with every frame turned about z (its ego turned the other way: poses R G R^-1) and, reversed,
    run backwards in time (frames and poses in reverse order, stamps counted from the new first frame)."""
    turn = turn_matrix(degrees)
    frames = [
        OccupancyFrame(np.ascontiguousarray(f.points @ turn[:3, :3].T), f.labels, f.index, f.stamp) for f in frames
    ]
    gt = turn @ np.asarray(gt) @ turn.T
    if direction == "reversed":
        frames, gt = frames[::-1], gt[::-1]
    return [OccupancyFrame(f.points, f.labels, i, i / 2.0) for i, f in enumerate(frames)], gt


def real_scene(name: str) -> tuple[list, np.ndarray]:
    from occvo_core.datasets import OccVOReleaseScene

    source = OccVOReleaseScene(SAMPLE / "occupancy" / name)
    return [source[i] for i in range(len(source))], np.asarray(source.gt_poses)


def occvo_eval(gt: np.ndarray, est: np.ndarray, tmp: Path) -> dict:
    """`occvo eval --fit-time-offset --json` on the trajectories, written as TUM files at 2 Hz stamps."""
    from occvo_cli.cli import main as occvo_main
    from occvo_core.trajectory import write_tum

    stamps = np.arange(len(gt)) / 2.0
    write_tum(tmp / "gt.tum", np.linalg.inv(gt[0]) @ gt, stamps)
    write_tum(tmp / "est.tum", est, stamps)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = occvo_main(
            ["eval", "--gt", str(tmp / "gt.tum"), "--est", str(tmp / "est.tum"), "--fit-time-offset", "--json"]
        )
    if code != 0:
        raise RuntimeError(f"occvo eval failed ({code}): {out.getvalue()}")
    return json.loads(out.getvalue())


def score_variant(frames: list, gt: np.ndarray, config: OccVOConfig) -> dict:
    vo = OccVO(config, threads=1)
    for frame in frames:
        vo.step(frame)
    est = vo.poses
    with tempfile.TemporaryDirectory(prefix="occvo-dihedral-") as tmp:
        e = occvo_eval(gt, est, Path(tmp))
    return {
        "ape_m": e["rmse"],
        "ape_time_fitted_m": e["ape_rmse_time_fitted_m"],
        "time_offset_ms": e["time_offset_ms"],
        "path_ratio": path_length(est) / path_length(np.linalg.inv(gt[0]) @ gt),
    }


def render(seed: int, cache: str) -> None:
    synthetic(seed, Path(cache))


def score(frames: list, gt: np.ndarray, config: OccVOConfig, truth_map=None) -> dict:
    vo = OccVO(config, threads=1)
    for frame in frames:
        vo.step(frame)
    est = vo.poses
    world_gt, gt = gt, np.linalg.inv(gt[0]) @ gt
    fit = fit_time_offset(gt, est, np.arange(len(gt)) / 2.0)
    row = {
        "ape_m": ape_rmse(gt, est),
        "ape_time_fitted_m": fit.ape_rmse_m,
        "time_offset_ms": fit.offset_ms,
        "path_ratio": path_length(est) / path_length(gt),
    }
    if truth_map is not None:
        from occvo_core.map_metrics import align_to_ground_truth, map_metrics

        points, labels = vo.map_points()
        m = map_metrics(align_to_ground_truth(points, est, world_gt), labels, *truth_map)  # the true map's frame
        row.update(precision=m.precision, completion=m.completion)
    return row


def job(args: tuple) -> tuple:
    spec, kind, key, cache = args
    config = load_config(spec)
    if kind == "dihedral":
        scene, degrees, direction = key
        frames, gt = real_scene(scene) if isinstance(scene, str) else synthetic(scene, Path(cache))[:2]
        return spec, kind, key, score_variant(*variant(frames, gt, degrees, direction), config)
    if kind == "real":
        name, way = key
        frames, gt = four_ways(SAMPLE, name)[way]
        return spec, kind, key, score(frames, gt, config)
    frames, gt, truth = synthetic(key, Path(cache))
    return spec, kind, key, score(frames, gt, config, truth)


def summarise(rows: dict) -> dict:
    apes = [r["ape_m"] for r in rows.values()]
    out = {
        "mean_ape_m": float(np.mean(apes)),
        "worst_ape_m": float(np.max(apes)),
        "success": float(np.mean([success(a) for a in apes])),
        "mean_ape_time_fitted_m": float(np.mean([r["ape_time_fitted_m"] for r in rows.values()])),
        "worst_ape_time_fitted_m": float(np.max([r["ape_time_fitted_m"] for r in rows.values()])),
        "mean_path_ratio": float(np.mean([r["path_ratio"] for r in rows.values()])),
    }
    for k in ("precision", "completion"):
        if all(k in r for r in rows.values()):
            out[f"mean_{k}"] = float(np.mean([r[k] for r in rows.values()]))
    return out


def dihedral_summary(rows: dict) -> dict:
    """Per scene (or seed) and time direction, the spread (max - min) over the four turns; per seed, the APE spread
    over all eight; over the real scenes and over the seeds, mean and worst."""
    out: dict = {"scenes": {}}
    figures = ("ape_m", "ape_time_fitted_m", "time_offset_ms")
    for scene in sorted({k[0] for k in rows}, key=str):
        entry = {}
        for direction in DIRECTIONS:
            runs = [rows[(scene, d, direction)] for d in TURNS]
            entry[direction] = {f"{f}_spread": float(np.ptp([r[f] for r in runs])) for f in figures}
        entry["ape_m_spread_all"] = float(np.ptp([r["ape_m"] for k, r in rows.items() if k[0] == scene]))
        out["scenes"][str(scene)] = entry
    for group, real in (("real", True), ("synthetic", False)):
        scenes = [k for k in {k[0] for k in rows} if isinstance(k, str) == real]
        if not scenes:
            continue
        sel = [r for k, r in rows.items() if k[0] in scenes]
        spreads = [out["scenes"][str(k)] for k in scenes]
        out[group] = {
            "mean_ape_m": float(np.mean([r["ape_m"] for r in sel])),
            "worst_ape_m": float(np.max([r["ape_m"] for r in sel])),
            "mean_ape_time_fitted_m": float(np.mean([r["ape_time_fitted_m"] for r in sel])),
            "worst_ape_time_fitted_m": float(np.max([r["ape_time_fitted_m"] for r in sel])),
            "worst_turn_spread_ape_m": max(e[d]["ape_m_spread"] for e in spreads for d in DIRECTIONS),
            "worst_turn_spread_ape_time_fitted_m": max(
                e[d]["ape_time_fitted_m_spread"] for e in spreads for d in DIRECTIONS
            ),
            "worst_turn_spread_time_offset_ms": max(e[d]["time_offset_ms_spread"] for e in spreads for d in DIRECTIONS),
            "worst_spread_all_ape_m": max(e["ape_m_spread_all"] for e in spreads),
        }
    return out


def leans(real: dict) -> dict:
    """Per scene: data offset d and ego-frame lean e from its four runs' best shifts (time_offset.py's algebra)."""
    out = {}
    for name in sorted({k[0] for k in real}):
        shifts = np.array([real[(name, w)]["time_offset_ms"] for w in RUNS])
        d, e = (np.array(list(RUNS.values()), np.float64).T @ shifts / 4.0)[:2]
        out[name] = {"data_offset_ms": float(d), "ego_lean_ms": float(e)}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument(
        "--sets", nargs="+", default=["real", "choose", "confirm"], choices=["dihedral", "real", "choose", "confirm"]
    )
    p.add_argument("--config", nargs="+", default=["default"], help="OccVOConfig JSON5 files, or 'default'")
    p.add_argument("--seeds", type=int, default=20, help="seeds of each synthetic set (the first N)")
    p.add_argument("--cache", default="/tmp/occvo-accuracy-cache")
    p.add_argument("--jobs", type=int, default=2)
    p.add_argument("--output", type=Path)
    args = p.parse_args(argv)
    fp = "pinned" if is_pinned() else "native"  # native: another CPU may give other last bits, other figures
    args.cache = str(Path(args.cache) / fp)
    print(f"floating point: {fp}")
    scenes = sorted(d.name for d in (SAMPLE / "occupancy").iterdir()) if (SAMPLE / "occupancy").is_dir() else []
    if ("real" in args.sets or "dihedral" in args.sets) and not scenes:
        print(f"no real scenes at {SAMPLE}", file=sys.stderr)
    keys = scenes + list(SETS["confirm"])[: args.seeds] if "dihedral" in args.sets else []
    jobs = [
        (c, "dihedral", (k, d, w), args.cache) for c in args.config for k in keys for w in DIRECTIONS for d in TURNS
    ]
    jobs += [(c, "real", (s, w), args.cache) for c in args.config if "real" in args.sets for s in scenes for w in RUNS]
    jobs += [
        (c, k, seed, args.cache)
        for c in args.config
        for k in ("choose", "confirm")
        if k in args.sets
        for seed in list(SETS[k])[: args.seeds]
    ]
    results: dict = {c: {} for c in args.config}
    with ProcessPoolExecutor(args.jobs) as pool:
        seeds = sorted(
            {key for _, kind, key, _ in jobs if kind in SETS}
            | {key[0] for _, kind, key, _ in jobs if kind == "dihedral" and not isinstance(key[0], str)}
        )
        list(pool.map(render, seeds, [args.cache] * len(seeds)))  # each seed once, before the runs that share it
        for spec, kind, key, row in pool.map(job, jobs):
            results[spec].setdefault(kind, {})[key] = row
    report = {}
    for spec, kinds in results.items():
        report[spec] = {}
        for kind, rows in kinds.items():
            entry = {
                "runs": {"/".join(map(str, k)) if isinstance(k, tuple) else str(k): r for k, r in rows.items()},
                "summary": dihedral_summary(rows) if kind == "dihedral" else summarise(rows),
            }
            if kind == "real":
                entry["leans"] = leans(rows)
            report[spec][kind] = entry
    print_report(report)
    if args.output:
        args.output.write_text(json.dumps(report, indent=1) + "\n")
    return 0


def print_report(report: dict) -> None:
    for spec, kinds in report.items():
        print(f"== {spec}")
        for kind, entry in kinds.items():
            if kind == "dihedral":
                print_dihedral(entry)
                continue
            s = entry["summary"]
            line = (
                f"  {kind:<8} APE mean {s['mean_ape_m']:.3f} worst {s['worst_ape_m']:.3f} | time-fitted mean "
                f"{s['mean_ape_time_fitted_m']:.3f} worst {s['worst_ape_time_fitted_m']:.3f} | path ratio "
                f"{s['mean_path_ratio']:.4f} | success {s['success']:.3f}"
            )
            if "mean_precision" in s:
                line += f" | precision {s['mean_precision']:.3f} completion {s['mean_completion']:.3f}"
            print(line)
            if kind == "real":
                for run, r in entry["runs"].items():
                    print(
                        f"    {run:<22} APE {r['ape_m']:.3f} fitted {r['ape_time_fitted_m']:.3f} "
                        f"shift {r['time_offset_ms']:+4.0f} ms path {r['path_ratio']:.4f}"
                    )
                for name, lean in entry["leans"].items():
                    print(
                        f"    {name}: data offset {lean['data_offset_ms']:+.0f} ms, ego lean {lean['ego_lean_ms']:+.0f} ms"
                    )


def print_dihedral(entry: dict) -> None:
    runs, summary = entry["runs"], entry["summary"]
    print("  dihedral: per variant APE / time-fitted APE (m) / best shift (ms); spread = max - min over the turns")
    for scene, spread in summary["scenes"].items():
        for direction in DIRECTIONS:
            cells = []
            for d in TURNS:
                r = runs[f"{scene}/{d}/{direction}"]
                cells.append(f"{r['ape_m']:.3f}/{r['ape_time_fitted_m']:.3f}/{r['time_offset_ms']:+4.0f}")
            sp = spread[direction]
            print(
                f"    {scene:<10} {direction:<8} " + "  ".join(cells) + f" | spread {sp['ape_m_spread']:.4f}/"
                f"{sp['ape_time_fitted_m_spread']:.4f}/{sp['time_offset_ms_spread']:.0f}"
            )
    for group in ("real", "synthetic"):
        if group in summary:
            g = summary[group]
            print(
                f"  dihedral {group:<9} APE mean {g['mean_ape_m']:.4f} worst {g['worst_ape_m']:.4f} | time-fitted mean "
                f"{g['mean_ape_time_fitted_m']:.4f} worst {g['worst_ape_time_fitted_m']:.4f} | worst spread over "
                f"turns: APE {g['worst_turn_spread_ape_m']:.4f} m, fitted "
                f"{g['worst_turn_spread_ape_time_fitted_m']:.4f} m, shift {g['worst_turn_spread_time_offset_ms']:.0f} ms | worst APE spread over all eight "
                f"{g['worst_spread_all_ape_m']:.4f}"
            )


if __name__ == "__main__":
    restart_pinned()
    sys.exit(main())
