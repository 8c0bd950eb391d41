"""Odometry on a TPV-Former checkpoint's predictions, by confidence threshold: which thresholds to serve with.

    python benchmarks/confidence.py --checkpoint DIR/checkpoint.pt --seeds 2000 2001 2002 2003 2004   # choose
    python benchmarks/confidence.py --checkpoint DIR/checkpoint.pt --seeds 1000 1001 1002 1003 1004 --pairs 0,0 0.9,0.95
    python benchmarks/confidence.py --checkpoint DIR/checkpoint.pt --pairs 0.9,0.95 --config default A.json5 B.json5

Each synthetic seed (40 frames, 2 Hz) is rendered and run through the network once (OccupancyPredictor.predict_labels);
then, for each (min_confidence, min_ground_confidence) pair, the voxels below it are set free (confident_labels, as
the predictor and the inference worker do), the camera mask keeps the voxels the cameras see (`--mask none`: all),
and OccVO runs over the frames, with the semantic BEV motion search on
(as `occvo run --from-images` has it), once per --config (JSON5 OccVOConfig overrides; "default" the built-in one).
Prints the APE RMSE (m) of every seed and the successes (APE < 5 m) per pair and config. Choose on seeds that are
neither training seeds (docs/model.md lists each run's) nor the held-out 1000-1004, then measure the chosen
pair on those.
"""

from __future__ import annotations

import argparse
import json
import sys

import torch

from occvo_core import OccVO, OccVOConfig
from occvo_core.eval import ape_rmse
from occvo_core.frame import OccupancyFrame
from occvo_core.grid import grid_to_points
from occvo_core.models.camera_mask import masked
from occvo_core.models.image_source import ImageOccupancySource
from occvo_core.models.tpvformer.predictor import OccupancyPredictor, confident_labels
from occvo_core.sim import SyntheticScene


def _config(name: str) -> OccVOConfig:
    config = OccVOConfig() if name == "default" else OccVOConfig.load(name)
    return config.with_motion_search()  # as occvo run --from-images has it


PAIRS = ["0,0", "0.8,0", "0.9,0", "0.8,0.9", "0.85,0.9", "0.9,0.9", "0.8,0.95", "0.85,0.95", "0.9,0.95"]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[2000, 2001, 2002, 2003, 2004])
    ap.add_argument("--pairs", nargs="+", default=PAIRS, help="min_confidence,min_ground_confidence")
    ap.add_argument("--config", nargs="+", default=["default"], help="OccVOConfig JSON5 files, or 'default'")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--mask", choices=("camera", "none"), default="camera", help="as occvo run --from-images --mask")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    configs = {name: _config(name) for name in args.config}
    pairs = [(name, *(float(v) for v in p.split(","))) for name in configs for p in args.pairs]
    predictor = OccupancyPredictor(args.checkpoint, device="cpu")
    ape = {p: [] for p in pairs}
    for seed in args.seeds:
        scene = SyntheticScene(seed=seed, frames=args.frames)
        source = ImageOccupancySource(scene, predictor)
        predicted = [predictor.predict_labels(*source.camera_frame(i)) for i in range(len(scene))]
        for p in pairs:
            vo = OccVO(configs[p[0]])
            for i, (labels, confidence) in enumerate(predicted):
                grid = confident_labels(labels, confidence, *p[1:]).to(torch.uint8).numpy()
                if args.mask == "camera":
                    rig = source.rig  # the rendered images' calibration, at the network's input size
                    grid = masked(grid, predictor.grid, rig.intrinsics, rig.cam_to_ego, predictor.cfg.input_size)
                points, classes = grid_to_points(grid)
                vo.step(OccupancyFrame(points, classes, i, float(scene.times[i]), {"seed": seed}))
            ape[p].append(ape_rmse(scene.gt_poses, vo.poses))
        print(f"seed {seed}: " + "  ".join(f"{_key(p)}: {ape[p][-1]:.2f}" for p in pairs), flush=True)
    head = f"{'config':<24} {'min_confidence':>14} {'ground':>6}  succeeded  mean  "
    print(f"\n{head}APE RMSE (m) of seeds {' '.join(map(str, args.seeds))}")
    for p in pairs:
        r = ape[p]
        mean = sum(r) / len(r)
        print(
            f"{p[0]:<24} {p[1]:>14g} {p[2]:>6g}  {sum(x < 5.0 for x in r)} of {len(r):<5} {mean:5.2f}  "
            f"{' '.join(f'{x:.2f}' for x in r)}"
        )
    print(json.dumps({"seeds": args.seeds, "ape_rmse_m": {_key(p): [round(x, 3) for x in ape[p]] for p in pairs}}))
    return 0


def _key(p: tuple) -> str:
    name, a, b = p
    return f"{a:g},{b:g}" if name == "default" else f"{name}:{a:g},{b:g}"


if __name__ == "__main__":
    sys.exit(main())
