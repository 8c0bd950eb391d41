"""occvo make-occupancy: Occ3D-style occupancy labels (semantics, mask_lidar, mask_camera) of a nuScenes drive's
keyframes from its aggregated LiDAR, written in Occ3D-nuScenes' layout (gts/<scene>/<token>/labels.npz and
annotations.json), which `open_scene(OUT, scene=S)` and `occvo run --input OUT --scene S` read."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def index_range(text: str) -> tuple[int, int]:
    """'A-B' (inclusive) or 'A' -> (A, B)."""
    first, _, last = text.partition("-")
    try:
        a, b = int(first), int(last or first)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a keyframe range A-B (e.g. 0-40)") from None
    if a < 0 or b < a:
        raise argparse.ArgumentTypeError(f"{text!r}: a range A-B needs 0 <= A <= B")
    return a, b


def add_parser(sub) -> None:
    p = sub.add_parser("make-occupancy", help="Occ3D-style occupancy labels of a nuScenes drive from its LiDAR")
    p.add_argument("--input", type=Path, required=True, help="nuScenes root in the devkit's layout (or an extract)")
    p.add_argument("--scene", help="the scene to label (default: the root's only scene)")
    p.add_argument("--version", help="the tables' folder, e.g. v1.0-mini (default: the only one)")
    p.add_argument("--keyframes", type=index_range, help="keyframes to write labels for, A-B (default: all)")
    p.add_argument(
        "--sweeps-from", type=index_range, help="keyframe sweeps aggregated, A-B (default: all of the scene's)"
    )
    p.add_argument("--out", type=Path, required=True, help="Occ3D root to write (gts/<scene>/ and annotations.json)")
    p.add_argument(
        "--pictures",
        type=Path,
        help="also write PNGs here: each camera with the keyframe's LiDAR points by class, and from above the labels "
        "beside the shipped camera model's prediction",
    )
    p.add_argument("--json", action="store_true", help="the summary as JSON on stdout instead of the table")
    p.add_argument("--quiet", action="store_true", help="no progress")
    p.set_defaults(func=run)


def keyframe_list(name: str, span: tuple[int, int] | None, n: int) -> list[int]:
    from occvo_core.errors import ConfigError

    if span is None:
        return list(range(n))
    if span[1] >= n:
        raise ConfigError(f"--{name} {span[0]}-{span[1]}: the scene has keyframes 0-{n - 1}")
    return list(range(span[0], span[1] + 1))


def run(args) -> int:
    from occvo_core.datasets.nuscenes_drive import NuScenesDrive
    from occvo_core.datasets.occ3d_nuscenes import ANNOTATIONS, read_annotations
    from occvo_core.datasets.occ3d_write import label_path, write_annotations, write_labels
    from occvo_core.lidar.label_stats import LabelStats
    from occvo_core.lidar.occ3d_labels import keyframe_labels, load_sweeps

    drive = NuScenesDrive(args.input, scene=args.scene, version=args.version)
    if (args.out / ANNOTATIONS).is_file():
        read_annotations(args.out)  # an annotations.json to merge into is checked before minutes of work, not after
    keyframes = keyframe_list("keyframes", args.keyframes, len(drive))
    sweeps = load_sweeps(drive, keyframe_list("sweeps-from", args.sweeps_from, len(drive)))
    stats = LabelStats()
    pictures = _Pictures(drive, args.pictures) if args.pictures is not None else None
    for n, i in enumerate(keyframes):
        labels = keyframe_labels(drive, sweeps, i)
        write_labels(label_path(args.out, drive.name, drive[i].token), labels.arrays())
        stats.add(labels)
        if pictures is not None:
            pictures.draw(i, labels)
        if not args.quiet:
            print(f"\rkeyframe {i} ({n + 1} of {len(keyframes)})", end="", file=sys.stderr, flush=True)
    if not args.quiet:
        print(file=sys.stderr)
    write_annotations(args.out, drive, keyframes)
    summary = {"scene": drive.name, "keyframes": [keyframes[0], keyframes[-1]], **stats.summary()}
    summary["sweeps"] = sorted(sweeps)[:: max(len(sweeps) - 1, 1)]
    print(json.dumps(summary, indent=1) if args.json else stats.table(drive.name, args.out))
    return 0


class _Pictures:
    """Per keyframe: a PNG a camera with its LiDAR points, and one from above of labels and the shipped model."""

    def __init__(self, drive, out: Path):
        from occvo_core.models.image_source import NuScenesImageSource
        from occvo_core.models.tpvformer.checkpoint import shipped_checkpoint
        from occvo_core.models.tpvformer.predictor import OccupancyPredictor

        self.out = out / drive.name
        self.out.mkdir(parents=True, exist_ok=True)
        self.drive, self.source = drive, NuScenesImageSource(drive, OccupancyPredictor(shipped_checkpoint()))

    def draw(self, index: int, labels) -> None:
        from occvo_core.viz.lidar_pictures import camera_pictures, top_pictures, top_view

        camera_pictures(self.drive, index, self.out)
        predicted = self.source.grid(index)
        panels = {
            "LiDAR labels": top_view(labels.semantics),
            "LiDAR labels, camera mask": top_view(labels.semantics, labels.mask_camera),
            "tiny's prediction, camera mask": top_view(predicted, labels.mask_camera),
        }
        top_pictures(panels, self.out / f"{index:03d}_above.png")
