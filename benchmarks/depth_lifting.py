"""The camera model on a real drive with and without depth lifting: the network's argmax, gated by the voxels its depth
head's lifted pixels land in (`gate`: the argmax kept there only; `lift`: the best occupied class there, whatever the
argmax), for several ranges, scored inside each keyframe's mask_camera against Occ3D-style labels.

    python benchmarks/depth_lifting.py --checkpoint CKPT --input ../shared/data/nuscenes-mini \
        --labels .train/labels-0-24 --keyframes 17-24 --ranges 10 20 30 40
"""

from __future__ import annotations

import argparse
import json

import numpy as np
import torch

from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.grid import FREE
from occvo_core.models.drive_eval import labels_by_token
from occvo_core.models.image_source import NuScenesImageSource
from occvo_core.models.metrics import OccMetrics
from occvo_core.models.tpvformer import OccupancyPredictor
from occvo_core.models.tpvformer.lifting import lifted_points, lifted_voxels


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--input", required=True)
    ap.add_argument("--labels", required=True)
    ap.add_argument("--keyframes", default="17-24")
    ap.add_argument("--ranges", type=float, nargs="+", default=[10, 20, 30, 40])
    ap.add_argument("--upsample", type=int, default=4)
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    a, b = (int(x) for x in args.keyframes.split("-"))
    predictor = OccupancyPredictor(args.checkpoint, device="cpu")
    model, cfg = predictor.model.eval(), predictor.cfg
    source = NuScenesImageSource(NuScenesDrive(args.input), predictor)
    labels, index = labels_by_token(args.labels, source.drive.name)
    modes = ["argmax"] + [f"{m} {r:g}" for r in args.ranges for m in ("gate", "lift")]
    metrics = {m: OccMetrics() for m in modes}
    for i in range(a, b + 1):
        semantics, mask, _ = labels.load(index[source.drive[i].token])
        images, k, e = source.camera_frame(i)
        x = torch.from_numpy(images).permute(0, 3, 1, 2).float().div(255.0)[None]
        kt, et = torch.from_numpy(np.asarray(k, np.float32))[None], torch.from_numpy(np.asarray(e, np.float32))[None]
        with torch.no_grad():
            planes, depth_prob = model.encode_with_depth(x, kt, et)
            logits = model.decode(planes)[0].permute(1, 2, 3, 0)
        argmax = logits.argmax(-1)
        best_occupied = logits[..., :FREE].argmax(-1)
        points = lifted_points(depth_prob[0], kt[0], et[0], images.shape[1:3], tuple(cfg.depth_range), args.upsample)
        metrics["argmax"].update(argmax.numpy().astype(np.uint8), semantics, mask)
        for r in args.ranges:
            hit = lifted_voxels(points, tuple(cfg.lower), tuple(cfg.upper), tuple(cfg.grid_shape), r)
            gate = torch.where(hit, argmax, FREE)
            lift = torch.where(hit, best_occupied, FREE)
            metrics[f"gate {r:g}"].update(gate.numpy().astype(np.uint8), semantics, mask)
            metrics[f"lift {r:g}"].update(lift.numpy().astype(np.uint8), semantics, mask)
    table = {m: {"geometry_iou": v.geometry_iou(), "miou": v.miou()} for m, v in metrics.items()}
    for m, v in table.items():
        print(f"{m:<10} geometry IoU {v['geometry_iou']:.3f}  mIoU {v['miou']:.3f}")
    print(json.dumps({"checkpoint": args.checkpoint, "keyframes": [a, b], "table": table}))


if __name__ == "__main__":
    main()
