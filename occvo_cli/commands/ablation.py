"""occvo ablation: Table II of the paper (filter combinations x success ratio and RMSE) over given scenes."""

from __future__ import annotations

import json
from pathlib import Path

from occvo_cli.paths import out_file


def add_parser(sub) -> None:
    p = sub.add_parser(
        "ablation", help="the paper's Table II over scenes: each filter combination's success ratio and RMSE"
    )
    p.add_argument("--input", type=Path, nargs="+", help="scene folders (OCC-VO release or Occ3D)")
    p.add_argument("--gt-dir", type=Path, help="folder of <scene>.kitti ground-truth trajectories")
    p.add_argument("--seeds", type=int, nargs="+", help="synthetic scene seeds (instead of --input), with map metrics")
    p.add_argument("--frames", type=int, default=40, help="synthetic scene length")
    p.add_argument("--noise", default="default", help="synthetic prediction noise preset")
    p.add_argument("--json", action="store_true", help="the rows as JSON on stdout instead of the table")
    p.add_argument(
        "--out",
        "--output",
        dest="out",
        type=out_file(),
        help="also write the rows as JSON to this file (--output: the old name)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    from tqdm import tqdm

    from occvo_core.ablation import filter_combinations, format_table, run_ablation
    from occvo_core.errors import ConfigError
    from occvo_core.io import write_text_atomic

    map_metrics = None
    if args.seeds:
        from occvo_core.map_metrics import evaluate_map_against_truth
        from occvo_core.sim import SyntheticScene

        sources = [SyntheticScene(seed=s, frames=args.frames, noise=args.noise) for s in args.seeds]
        map_metrics = evaluate_map_against_truth
    elif args.input:
        from occvo_core.datasets import open_scene

        sources = [open_scene(p, gt=(args.gt_dir / f"{p.name}.kitti") if args.gt_dir else None) for p in args.input]
        missing = [s.name for s in sources if s.gt_poses is None]
        if missing:
            raise ConfigError(f"no ground truth for {', '.join(missing)}: give --gt-dir with <scene>.kitti files")
    else:
        raise ConfigError("give scene folders with --input (and --gt-dir) or synthetic --seeds")
    bar = tqdm(total=len(sources) * len(filter_combinations()), desc="ablation", unit="run", disable=args.quiet)
    rows = run_ablation(sources, map_metrics=map_metrics, progress=bar.update)
    bar.close()
    print(json.dumps(rows, indent=2, default=float) if args.json else format_table(rows))
    if args.out:
        write_text_atomic(args.out, json.dumps(rows, indent=2, default=float) + "\n")
    return 0
