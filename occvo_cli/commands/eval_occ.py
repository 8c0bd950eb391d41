"""occvo eval-occ: Occ3D-style mIoU (17 semantic classes) and geometry IoU of a TPV-Former checkpoint on held-out
synthetic seeds, or (--input DRIVE --labels DIR) on a nuScenes drive's real images against Occ3D-style labels."""

from __future__ import annotations

import json
from pathlib import Path

from occvo_cli.commands.make_occupancy import index_range, keyframe_list
from occvo_cli.paths import out_file


def add_parser(sub) -> None:
    p = sub.add_parser("eval-occ", help="mIoU and geometry IoU of a TPV-Former checkpoint inside the camera mask")
    p.add_argument(
        "--checkpoint",
        type=Path,
        help="default: the shipped checkpoint (with --input the one trained on real images, else tiny)",
    )
    p.add_argument(
        "--seeds", type=int, nargs="+", default=[1000, 1001, 1002, 1003, 1004], help="held-out synthetic seeds"
    )
    p.add_argument("--frames", type=int, default=20, help="frames per scene")
    p.add_argument("--stride", type=int, default=5, help="evaluate every n-th frame")
    p.add_argument("--input", type=Path, help="a nuScenes drive (devkit layout): score on its six real cameras")
    p.add_argument("--labels", type=Path, help="with --input: Occ3D-style labels of the drive (make-occupancy --out)")
    p.add_argument("--scene", help="with --input: the drive's scene (default: its only one)")
    p.add_argument("--keyframes", type=index_range, help="with --input: keyframes A-B to score (default: all)")
    p.add_argument("--device", help="cpu or cuda (default: cuda when present)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    p.add_argument("--json", action="store_true", help="the metrics as JSON on stdout instead of the table")
    p.add_argument(
        "--out",
        "--output",
        dest="out",
        type=out_file(),
        help="also write the metrics as JSON to this file (--output: the old name)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args) -> int:
    import torch

    from occvo_core.errors import DatasetError
    from occvo_core.io import write_text_atomic
    from occvo_core.models.tpvformer import load_checkpoint, select_device
    from occvo_core.models.tpvformer.checkpoint import served_model
    from occvo_core.models.train import evaluate

    args.checkpoint = args.checkpoint or served_model(real_rig=args.input is not None)[0]
    if not args.checkpoint.is_file():
        raise DatasetError(args.checkpoint, "no such checkpoint: give a file `occvo train-occ` wrote")
    torch.set_num_threads(args.threads)
    device = select_device(args.device)
    if args.input is not None or args.labels is not None:
        summary, where = _on_drive(args, device)
    else:
        model = load_checkpoint(args.checkpoint, device=device)
        metrics = evaluate(
            model, args.seeds, frames=args.frames, stride=args.stride, device=device, progress=not args.quiet
        )
        summary = metrics.summary()
        summary.update({"checkpoint": str(args.checkpoint), "seeds": args.seeds})
        where = f"seeds {args.seeds}"
    if args.out:
        write_text_atomic(args.out, json.dumps(summary, indent=1))
    if args.json:
        print(json.dumps(summary, indent=1))
        return 0
    width = max(len(k) for k in summary["per_class_iou"])
    for name, iou in summary["per_class_iou"].items():
        print(f"  {name:<{width}}  {'  n/a' if iou is None else f'{iou:.3f}'}")  # fractions, as the docs give them
    print(
        f"mIoU (17 classes): {summary['miou']:.3f}   geometry IoU: {summary['geometry_iou']:.3f}   "
        f"({summary['frames']} frames, {where}, inside the camera mask)"
    )
    return 0


def _on_drive(args, device) -> tuple[dict, str]:
    """The checkpoint's argmax on the drive's real images against the labels, inside their mask_camera."""
    import sys

    from occvo_core.datasets.nuscenes_drive import NuScenesDrive
    from occvo_core.errors import ConfigError
    from occvo_core.models.drive_eval import evaluate_drive
    from occvo_core.models.image_source import NuScenesImageSource
    from occvo_core.models.tpvformer.predictor import OccupancyPredictor

    if args.input is None or args.labels is None:
        raise ConfigError("scoring on a drive needs both --input DRIVE and --labels DIR (occvo make-occupancy --out)")
    drive = NuScenesDrive(args.input, scene=args.scene)
    keyframes = keyframe_list("keyframes", args.keyframes, len(drive))
    source = NuScenesImageSource(drive, OccupancyPredictor(args.checkpoint, device=str(device)))
    shown = None if args.quiet else (lambda i: print(f"\reval-occ keyframe {i}", end="", file=sys.stderr))
    summary = evaluate_drive(source, args.labels, keyframes, shown).summary()
    if shown:
        print(file=sys.stderr)
    span = f"keyframes {keyframes[0]}-{keyframes[-1]}"
    summary.update(
        {"checkpoint": str(args.checkpoint), "scene": drive.name, "keyframes": [keyframes[0], keyframes[-1]]}
    )
    return summary, f"{drive.name} {span}"
