"""The depth head on a real drive against its projected LiDAR: each pixel's most likely depth (as depth lifting
takes it, at the input resolution) against the depth of the nearest LiDAR return in that pixel, by distance band.

    python benchmarks/depth_accuracy.py --checkpoint CKPT --input ../shared/data/nuscenes-mini \
        --labels .train/labels-0-24 --keyframes 17-24
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from occvo_core.datasets.nuscenes_drive import NuScenesDrive
from occvo_core.models.drive_training import DriveFrames
from occvo_core.models.tpvformer import load_checkpoint
from occvo_core.models.tpvformer.lifting import lifted_points

BANDS = ((0, 10), (10, 20), (20, 30), (30, 60))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--checkpoint", required=True)
    ap.add_argument("--input", required=True, help="the nuScenes drive")
    ap.add_argument("--labels", required=True, help="its make-occupancy labels (DriveFrames needs them)")
    ap.add_argument("--keyframes", default="17-24")
    ap.add_argument("--threads", type=int, default=1)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    a, b = (int(x) for x in args.keyframes.split("-"))
    model = load_checkpoint(args.checkpoint).eval()
    cfg, (w, h) = model.cfg, model.cfg.input_size
    frames = DriveFrames.from_drive(NuScenesDrive(args.input), args.labels, range(a, b + 1), (w, h), stored=(w, h))
    pairs = {band: [] for band in BANDS}
    v, u = np.mgrid[0:h, 0:w]
    for n in range(len(frames)):
        s = frames.sample(n)
        with torch.no_grad():
            _, prob = model.encode_with_depth(s.images[None], s.intrinsics[None], s.cam_to_ego[None])
        up = h // prob.shape[-2]  # the finest level's stride: one lifted point per input pixel
        pts = lifted_points(prob[0], s.intrinsics, s.cam_to_ego, (h, w), tuple(cfg.depth_range), up)
        e = s.cam_to_ego
        pred = torch.einsum("nji,nhwj->nhwi", e[:, :3, :3], pts - e[:, None, None, :3, 3])[..., 2].numpy()
        k = s.intrinsics.numpy()
        for c in range(6):
            ok = np.isfinite(s.depth[c])  # ray length of the pixel's nearest return -> depth along the axis
            z = s.depth[c][ok] / np.sqrt(
                ((u[ok] - k[c, 0, 2]) / k[c, 0, 0]) ** 2 + ((v[ok] - k[c, 1, 2]) / k[c, 1, 1]) ** 2 + 1
            )
            for lo, hi in BANDS:
                sel = (z >= lo) & (z < hi)
                pairs[(lo, hi)].append(np.stack([z[sel], pred[c][ok][sel]], 1))
    print(f"{args.checkpoint}, keyframes {a}-{b}: predicted / LiDAR depth per pixel with a return")
    for (lo, hi), p in pairs.items():
        z, d = np.concatenate(p).T
        rel = np.abs(d - z) / z
        print(
            f"{lo:>2}-{hi} m  pixels {len(z):>6}  median ratio {np.median(d / z):.2f}  AbsRel {rel.mean():.2f}  "
            f"within 10 % {np.mean(rel < 0.1):.2f}  within 25 % {np.mean(rel < 0.25):.2f}"
        )


if __name__ == "__main__":
    main()
