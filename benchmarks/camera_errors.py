"""Where the camera model goes wrong on a real drive: occupancy against the LiDAR labels by distance and by height
(inside mask_camera), its depth head against the projected LiDAR (the depth scale), and pictures a person can check.

    python benchmarks/camera_errors.py --checkpoint CKPT --labels .train/labels-all --keyframes 25-40 --out DIR

Writes DIR/lidar_in_images.png (keyframe A's LiDAR projected into the six images, coloured by depth, above the
network's own expected depth) and DIR/top_view.png (from above: the labels, the prediction inside their camera mask,
the whole prediction; occvo_core.viz.lidar_pictures), and prints the tables (--json: as JSON).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np
import torch

from occvo_cli.commands.make_occupancy import index_range
from occvo_core.grid import FREE

DRIVE = Path(__file__).resolve().parents[2] / "shared" / "data" / "nuscenes-mini"
BANDS = ((0, 10), (10, 20), (20, 30), (30, 60))


def _expected_depth(probs: torch.Tensor, depth_range) -> torch.Tensor:
    """(Ncam, bins, h, w) log-spaced bin probabilities -> expected depth (Ncam, h, w), bin centres as the loss's."""
    near, far = depth_range
    bins = probs.shape[1]
    centres = near * torch.exp((torch.arange(bins) + 0.5) / bins * math.log(far / near))
    return (probs * centres.view(1, -1, 1, 1)).sum(1)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", type=Path, required=True)
    p.add_argument("--labels", type=Path, required=True, help="occvo make-occupancy --out of those keyframes")
    p.add_argument("--keyframes", type=index_range, default=(25, 40))
    p.add_argument("--drive", type=Path, default=DRIVE)
    p.add_argument("--out", type=Path, help="folder for the two pictures")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    torch.set_num_threads(1)
    from occvo_core.datasets.nuscenes_drive import NuScenesDrive
    from occvo_core.models.drive_eval import labels_by_token
    from occvo_core.models.drive_training import lidar_targets
    from occvo_core.models.image_source import NuScenesImageSource
    from occvo_core.models.metrics import OccMetrics
    from occvo_core.models.tpvformer.predictor import OccupancyPredictor

    drive = NuScenesDrive(args.drive)
    predictor = OccupancyPredictor(args.checkpoint, device="cpu")
    source = NuScenesImageSource(drive, predictor)
    labels, index = labels_by_token(args.labels, drive.name)
    model, cfg = predictor.model, predictor.cfg
    captured = {}
    model.depth_head.register_forward_hook(lambda _m, _i, out: captured.__setitem__("depth", out))
    centres = (np.arange(200) + 0.5) * 0.4 - 40
    reach = np.hypot(centres[:, None], centres[None, :])[..., None]
    bands = {b: np.zeros(3) for b in BANDS}
    heights = np.zeros((16, 3))
    metrics = OccMetrics()
    ratios = {b: [] for b in BANDS}
    first = args.keyframes[0]
    for i in range(args.keyframes[0], args.keyframes[1] + 1):
        semantics, mask, _ = labels.load(index[drive[i].token])
        images, k, e = source.camera_frame(i)
        grid = predictor.predict_grid(images, k, e)
        metrics.update(grid, semantics, mask)
        pred, true = (grid != FREE) & mask, (semantics != FREE) & mask
        for b in BANDS:
            m = (reach >= b[0]) & (reach < b[1])
            bands[b] += [(pred & true & m).sum(), (pred & ~true & m).sum(), (~pred & true & m).sum()]
        heights += np.stack([(pred & true).sum((0, 1)), (pred & ~true).sum((0, 1)), (~pred & true).sum((0, 1))], 1)
        # depth: the network's expected depth at each LiDAR return, against the return's (along the optical axis)
        rig = drive.rig(i).scaled(*cfg.input_size)
        sweep = drive.lidar_in_ego(i)
        moved = [sweep @ t[:3, :3].T + t[:3, 3] for t in (drive.ego_at_camera(i, c) for c in range(6))]
        ray, _ = lidar_targets(moved, [np.zeros(len(sweep), np.uint8)] * 6, rig)
        probs = torch.nn.functional.interpolate(
            captured["depth"].softmax(1), size=ray.shape[-2:], mode="bilinear", align_corners=False
        )
        guess = _expected_depth(probs, cfg.depth_range).numpy()
        v, u = np.mgrid[: ray.shape[1], : ray.shape[2]]
        for c in range(6):
            kk = rig.intrinsics[c]
            z = ray[c] / np.sqrt(((u - kk[0, 2]) / kk[0, 0]) ** 2 + ((v - kk[1, 2]) / kk[1, 1]) ** 2 + 1)
            ok = np.isfinite(z)
            for b in BANDS:
                sel = ok & (z >= b[0]) & (z < b[1])
                ratios[b].extend((guess[c][sel] / z[sel]).tolist())
        if i == first and args.out is not None:
            _pictures(args.out, images, ray, guess, grid, semantics, mask)
    table = {
        "keyframes": list(args.keyframes),
        "checkpoint": str(args.checkpoint),
        **metrics.summary(),
        "by_distance": {
            f"{a}-{b} m": {
                "iou": tp / max(tp + fp + fn, 1),
                "precision": tp / max(tp + fp, 1),
                "recall": tp / max(tp + fn, 1),
                "true_voxels": int(tp + fn),
            }
            for (a, b), (tp, fp, fn) in bands.items()
        },
        "by_height": {
            f"{-1 + 0.4 * z:+.1f} m": {"predicted": int(tp + fp), "true": int(tp + fn), "both": int(tp)}
            for z, (tp, fp, fn) in enumerate(heights)
        },
        "depth_ratio_median": {f"{a}-{b} m": float(np.median(r)) if r else None for (a, b), r in ratios.items()},
    }
    if args.json:
        print(json.dumps(table, indent=1))
        return 0
    print(f"{args.checkpoint}: keyframes {args.keyframes[0]}-{args.keyframes[1]}")
    print(f"geometry IoU {table['geometry_iou']:.3f}  mIoU {table['miou']:.3f}")
    print("per class: " + ", ".join(f"{k} {v:.3f}" for k, v in table["per_class_iou"].items() if v is not None))
    for name, row in table["by_distance"].items():
        depth = table["depth_ratio_median"][name]
        print(
            f"{name:>8}: IoU {row['iou']:.3f} precision {row['precision']:.3f} recall {row['recall']:.3f} "
            f"({row['true_voxels']} true voxels); depth head / LiDAR median {depth:.2f}"
        )
    for name, row in table["by_height"].items():
        print(f"z {name}: predicted {row['predicted']:6d} true {row['true']:6d} both {row['both']:6d}")
    return 0


def _pictures(out: Path, images, ray, guess, grid, semantics, mask) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    fig, axes = plt.subplots(2, 6, figsize=(18, 4.2))
    for c in range(6):
        axes[0, c].imshow(images[c])
        v, u = np.nonzero(np.isfinite(ray[c]))
        axes[0, c].scatter(u, v, c=ray[c][v, u], s=0.3, cmap="turbo", vmin=0, vmax=40)
        axes[1, c].imshow(guess[c], cmap="turbo", vmin=0, vmax=40)
        for a in axes[:, c]:
            a.axis("off")
    axes[0, 0].set_title("LiDAR projected (depth 0-40 m)", loc="left", fontsize=9)
    axes[1, 0].set_title("network's expected depth", loc="left", fontsize=9)
    fig.tight_layout()
    fig.savefig(out / "lidar_in_images.png", dpi=80)
    plt.close(fig)

    from occvo_core.viz.lidar_pictures import top_pictures, top_view

    panels = {
        "LiDAR labels in mask_camera": top_view(semantics, mask),
        "prediction in mask_camera": top_view(grid, mask),
        "prediction": top_view(grid),
    }
    top_pictures(panels, out / "top_view.png")


if __name__ == "__main__":
    raise SystemExit(main())
