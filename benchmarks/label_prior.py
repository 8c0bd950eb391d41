"""The label prior, a reference for the camera model on a real drive: each voxel of the ego-frame grid occupied where
the training keyframes' labels had it occupied often enough (per-voxel frequency over the keyframes whose camera mask
saw it, or over all of them), with the class it held most often. Scored as `occvo eval-occ` scores a checkpoint
(OccMetrics inside each keyframe's mask_camera), whole and by distance band; with --checkpoint the model's argmax is
scored by the same bands beside it.

    python benchmarks/label_prior.py --prior-labels .train/labels-0-24 --prior-keyframes 0-16 \
        --labels .train/labels-0-24 --keyframes 17-24 --thresholds 0.1 0.2 0.3 0.4 0.5
    python benchmarks/label_prior.py --prior-labels .train/labels-0-24 --prior-keyframes 0-24 \
        --labels .train/labels-all --keyframes 25-40 --thresholds 0.3 --checkpoint CKPT

--own-sweeps ROOT scores, beside, each keyframe's own LiDAR sweep labelled alone (ROOT/<i> from `occvo make-occupancy
--keyframes i-i --sweeps-from i-i --out ROOT/i`): what a perfect copy of the sensor at that instant scores.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from occvo_cli.commands.make_occupancy import index_range
from occvo_core.grid import FREE, NUM_CLASSES

DRIVE = Path(__file__).resolve().parents[2] / "shared" / "data" / "nuscenes-mini"
BANDS = ((0, 10), (10, 20), (20, 40))


def label_grids(drive, labels_root: Path, keyframes: tuple[int, int]):
    """(semantics, mask_camera) of each keyframe A..B, from an occvo make-occupancy folder."""
    from occvo_core.models.drive_eval import labels_by_token

    labels, index = labels_by_token(labels_root, drive.name)
    for i in range(keyframes[0], keyframes[1] + 1):
        semantics, mask, _ = labels.load(index[drive[i].token])
        yield i, semantics, np.asarray(mask, bool)


def build_prior(grids, observed_only: bool) -> tuple[np.ndarray, np.ndarray]:
    """Per voxel: occupancy frequency (over the keyframes that saw it, or over all) and the most frequent class."""
    counts = obs = None
    for _, semantics, mask in grids:
        if counts is None:
            counts = np.zeros((*semantics.shape, NUM_CLASSES), np.int32)
            obs = np.zeros(semantics.shape, np.int32)
        seen = mask if observed_only else np.ones_like(mask)
        flat = counts.reshape(-1, NUM_CLASSES)
        idx = np.flatnonzero(seen)
        np.add.at(flat, (idx, semantics.ravel()[idx].astype(np.int64)), 1)
        obs += seen
    occupied = counts[..., :FREE].sum(-1)
    freq = occupied / np.maximum(obs, 1)
    return freq, counts[..., :FREE].argmax(-1)


def banded(grid, semantics, mask, bands, metrics_by_band):
    centres = (np.arange(200) + 0.5) * 0.4 - 40
    reach = np.hypot(centres[:, None], centres[None, :])[..., None]
    for band in bands:
        m = mask & (reach >= band[0]) & (reach < band[1])
        metrics_by_band[band].update(grid, semantics, m)


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--drive", type=Path, default=DRIVE)
    p.add_argument("--prior-labels", type=Path, required=True, help="labels the prior is built from")
    p.add_argument("--prior-keyframes", type=index_range, required=True)
    p.add_argument("--labels", type=Path, required=True, help="labels scored against")
    p.add_argument("--keyframes", type=index_range, required=True)
    p.add_argument("--thresholds", type=float, nargs="+", default=[0.3])
    p.add_argument("--all-frames", action="store_true", help="frequency over all prior keyframes, not only seen")
    p.add_argument("--checkpoint", type=Path, help="also score this model's argmax by the same bands")
    p.add_argument("--own-sweeps", type=Path, help="ROOT/<i>: keyframe i labelled from its own sweep alone")
    p.add_argument("--json", action="store_true")
    args = p.parse_args()
    from occvo_core.datasets.nuscenes_drive import NuScenesDrive
    from occvo_core.models.metrics import OccMetrics

    drive = NuScenesDrive(args.drive)
    freq, majority = build_prior(
        label_grids(drive, args.prior_labels, args.prior_keyframes), observed_only=not args.all_frames
    )
    bands = [(0, 1000), *BANDS]
    rows = {t: {b: OccMetrics() for b in bands} for t in args.thresholds}
    model_rows = {b: OccMetrics() for b in bands}
    sweep_rows = {b: OccMetrics() for b in bands}
    source = None
    if args.checkpoint is not None:
        import torch

        from occvo_core.models.image_source import NuScenesImageSource
        from occvo_core.models.tpvformer.predictor import OccupancyPredictor

        torch.set_num_threads(1)
        source = NuScenesImageSource(drive, OccupancyPredictor(args.checkpoint, device="cpu"))
    for i, semantics, mask in label_grids(drive, args.labels, args.keyframes):
        for t in args.thresholds:
            grid = np.where(freq >= t, majority, FREE).astype(np.uint8)
            banded(grid, semantics, mask, bands, rows[t])
        if source is not None:
            banded(source.grid(i), semantics, mask, bands, model_rows)
        if args.own_sweeps is not None:
            (_, own, _), *_ = label_grids(drive, args.own_sweeps / str(i), (i, i))
            banded(own, semantics, mask, bands, sweep_rows)

    def name(b):
        return "all" if b[1] == 1000 else f"{b[0]}-{b[1]} m"

    def summary(ms):
        return {name(b): {"iou": m.geometry_iou(), "miou": m.miou()} for b, m in ms.items()}

    table = {f"prior >= {t}": summary(ms) for t, ms in rows.items()}
    if source is not None:
        table[str(args.checkpoint)] = summary(model_rows)
    if args.own_sweeps is not None:
        table["own sweep"] = summary(sweep_rows)
    if args.json:
        print(json.dumps(table, indent=1))
        return 0
    print(f"prior from keyframes {args.prior_keyframes}, scored on {args.keyframes} ({args.labels})")
    for row, cells in table.items():
        print(f"{row}: " + "; ".join(f"{k} IoU {v['iou']:.3f} mIoU {v['miou']:.3f}" for k, v in cells.items()))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
