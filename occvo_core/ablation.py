"""The paper's Table II (filters x success ratio, RMSE), with Table IV's map metrics where a true map exists."""

from __future__ import annotations

import itertools

import numpy as np

from occvo_core.config import OccVOConfig
from occvo_core.eval import ape_rmse, success_ratio
from occvo_core.odometry import OccVO

FILTERS = ("semantic", "dynamic", "pfilter")


def filter_combinations() -> list[dict[str, bool]]:
    """All eight on/off combinations, none first and all last (the paper's row order)."""
    combos = [dict(zip(FILTERS, bits)) for bits in itertools.product((False, True), repeat=3)]
    return sorted(combos, key=lambda c: (sum(c.values()), [not c[f] for f in FILTERS]))


def run_ablation(sources, base: OccVOConfig | None = None, map_metrics=None, progress=None) -> list[dict]:
    """One row a filter combination: per-scene RMSE, success ratio, mean RMSE (and map metrics if given a function)."""
    base = base or OccVOConfig()
    frames = {s.name: [s[i] for i in range(len(s))] for s in sources}
    rows = []
    for combo in filter_combinations():
        cfg = base.with_filters(**combo)
        rmses, maps = {}, []
        for source in sources:
            vo = OccVO(cfg)
            for frame in frames[source.name]:
                vo.step(frame)
            rmses[source.name] = ape_rmse(source.gt_poses[vo.frame_indices], vo.poses)
            if map_metrics is not None:
                maps.append(map_metrics(source, vo))
            if progress:
                progress()
        row = {
            **combo,
            "rmse": rmses,
            "success_ratio": success_ratio(rmses.values()),
            "mean_rmse": float(np.mean(list(rmses.values()))),
        }
        if maps:
            row["map"] = {k: float(np.mean([m[k] for m in maps])) for k in ("accuracy", "precision", "completion")}
        rows.append(row)
    return rows


def format_table(rows: list[dict]) -> str:
    mark = lambda on: "  x " if on else "    "  # noqa: E731
    scenes = list(rows[0]["rmse"])
    head = "| Semantic | Dynamic | PFilter | Success | RMSE (m) |"
    if "map" in rows[0]:
        head += " Acc. (m) | Prec. | Compl. |"
    if len(scenes) <= 6:
        head += "".join(f" {s} |" for s in scenes)
    lines = [head, "|" + "|".join("---" for _ in head.split("|")[1:-1]) + "|"]
    for r in rows:
        line = (
            f"| {mark(r['semantic'])} | {mark(r['dynamic'])} | {mark(r['pfilter'])} | {r['success_ratio']:.3f} |"
            f" {r['mean_rmse']:.3f} |"
        )
        if "map" in r:
            line += f" {r['map']['accuracy']:.3f} | {r['map']['precision']:.3f} | {r['map']['completion']:.3f} |"
        if len(scenes) <= 6:
            line += "".join(f" {r['rmse'][s]:.3f} |" for s in scenes)
        lines.append(line)
    return "\n".join(lines)
