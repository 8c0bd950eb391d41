"""occvo train-occ: train TPV-Former for a time budget on synthetic scenes (images rendered from the true occupancy),
mixed with a real nuScenes drive's keyframes (--drive: LiDAR labels as voxel targets, projected LiDAR as depth)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from occvo_cli.commands.make_occupancy import index_range
from occvo_cli.paths import out_dir


def add_parser(sub) -> None:
    p = sub.add_parser("train-occ", help="train the TPV-Former occupancy network on synthetic scenes")
    p.add_argument("--preset", default="tiny", help="network preset: tiny or paper")
    p.add_argument("--minutes", type=float, required=True, help="wall-clock training budget")
    p.add_argument(
        "--out", type=out_dir, required=True, help="output folder: checkpoint.pt, loss_curve.png, train_log.json"
    )
    p.add_argument(
        "--seeds",
        type=int,
        nargs="*",
        default=list(range(20)),
        help="synthetic training scene seeds (none: the drive's keyframes alone)",
    )
    p.add_argument("--frames", type=int, default=20, help="frames per scene")
    p.add_argument("--stride", type=int, default=2, help="use every n-th frame")
    p.add_argument("--lr", type=float, default=2e-3, help="AdamW learning rate (default 2e-3)")
    p.add_argument("--max-steps", type=int, help="stop after this many steps even within the budget")
    p.add_argument(
        "--cache", type=out_dir, help="keep rendered training frames here (.npz) and reuse them in later runs"
    )
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (the machine is shared)")
    p.add_argument(
        "--prerender",
        type=int,
        metavar="JOBS",
        help="first render every training frame into --cache in JOBS "
        "processes, before the training clock starts (rendering is data making, not training)",
    )
    p.add_argument("--drive", type=Path, help="a nuScenes drive (devkit layout) whose keyframes are trained on too")
    p.add_argument("--drive-scene", help="the drive's scene (default: its only one)")
    p.add_argument("--drive-keyframes", type=index_range, help="the drive's keyframes to train on, A-B (default: all)")
    p.add_argument(
        "--drive-labels", type=Path, help="Occ3D-style labels of those keyframes (occvo make-occupancy --out)"
    )
    p.add_argument(
        "--drive-cache",
        type=Path,
        metavar="FILE",
        help="the drive's training frames as one .npz: read when it exists (no --drive needed), else made from "
        "--drive and written here",
    )
    p.add_argument("--real-fraction", type=float, default=0.5, help="share of steps on a real keyframe (default 0.5)")
    p.add_argument(
        "--depth-weight",
        type=float,
        default=1.0,
        help="weight of the depth head's loss (projected LiDAR or rendered depth) against the pixel-class loss; "
        "both are then weighed 0.5 against the voxel loss (default 1)",
    )
    p.add_argument(
        "--depth-only",
        action="store_true",
        help="train the image branch alone (backbone, depth head, pixel classes: no voxels), a small part of a "
        "step's cost; needs depth targets (a drive or rendered frames)",
    )
    p.add_argument(
        "--label-prior",
        type=float,
        metavar="WEIGHT",
        help="add a learned per-voxel free-logit offset, initialised to WEIGHT x the log-odds of the drive keyframes' "
        "label occupancy frequency (relative to --label-prior-threshold); needs a drive",
    )
    p.add_argument(
        "--label-prior-threshold", type=float, default=0.4, help="frequency the offset is 0 at (default 0.4)"
    )
    p.add_argument("--device", default="cpu", help="cpu or cuda (bf16 mixed precision on cuda)")
    p.add_argument(
        "--json", action="store_true", help="steps, seconds, losses and the checkpoint path as JSON on stdout"
    )
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument(
        "--resume",
        type=Path,
        metavar="CKPT",
        help="continue from this checkpoint (and the .state.pt beside "
        "it: optimizer, step count, loss history); --minutes is this run's budget",
    )
    p.set_defaults(func=run)


def run(args) -> int:
    import torch

    from occvo_core.errors import ConfigError
    from occvo_core.models.tpvformer import preset
    from occvo_core.models.train import train

    if not args.minutes > 0:
        raise ConfigError(f"--minutes must be positive, got {args.minutes}")
    torch.set_num_threads(args.threads)
    cfg = preset(args.preset)
    real, meta = _drive_frames(args, cfg.input_size)
    if args.depth_weight != 1.0:
        meta = {**(meta or {}), "depth_weight": args.depth_weight}
    if args.depth_only:
        meta = {**(meta or {}), "depth_only": True}
    prior = None
    if args.label_prior is not None or (args.resume is not None and _has_prior(args.resume)):
        cfg = cfg.model_copy(update={"label_prior": True})
    if args.label_prior is not None:
        from occvo_core.models.label_prior import free_prior, occupancy_frequency

        if not 0 < args.label_prior_threshold < 1:
            raise ConfigError(f"--label-prior-threshold must be in (0, 1), got {args.label_prior_threshold}")
        if real is None:
            raise ConfigError("--label-prior needs a drive's labels (--drive or --drive-cache)")
        shape = cfg.decode_shape or cfg.grid_shape
        frequency = occupancy_frequency(real.arrays["semantics"])
        prior = free_prior(frequency, shape, args.label_prior_threshold, args.label_prior)
        meta = {**meta, "label_prior": {"weight": args.label_prior, "threshold": args.label_prior_threshold}}
    if real is None and not args.seeds:
        raise ConfigError("nothing to train on: give --seeds, or a drive (--drive or --drive-cache)")
    if not 0.0 <= args.real_fraction <= 1.0:
        raise ConfigError(f"--real-fraction must be in [0, 1], got {args.real_fraction}")
    if args.prerender:
        if args.cache is None:
            raise ConfigError("--prerender needs --cache DIR (the frames are rendered there)")
        from occvo_core.models.training_data import prerender

        n = prerender(
            args.seeds, args.frames, args.stride, cfg.input_size, args.cache, args.prerender, progress=not args.quiet
        )
        print(f"occvo train-occ: prerendered {n} frames of {len(args.seeds)} seeds into {args.cache}", file=sys.stderr)
    result = train(
        cfg,
        args.out,
        args.minutes,
        args.seeds,
        frames=args.frames,
        stride=args.stride,
        lr=args.lr,
        max_steps=args.max_steps,
        preset_name=args.preset,
        cache_dir=args.cache,
        progress=not args.quiet,
        resume=args.resume,
        real=real,
        real_fraction=args.real_fraction,
        device=args.device,
        depth_weight=args.depth_weight,
        depth_only=args.depth_only,
        meta=meta,
        label_prior=prior,
    )
    tail = sum(result.losses[-20:]) / max(1, len(result.losses[-20:]))
    if args.json:
        print(
            json.dumps(
                {
                    "steps": result.steps,
                    "seconds": result.seconds,
                    "loss_first": result.losses[0],
                    "loss_last20_mean": tail,
                    "checkpoint": str(result.checkpoint),
                    "loss_curve": str(Path(args.out) / "loss_curve.png"),
                }
            )
        )
        return 0
    print(
        f"trained {result.steps} steps in {result.seconds / 60:.1f} min; loss {result.losses[0]:.3f} -> {tail:.3f} (mean of last 20)"
    )
    print(f"checkpoint: {result.checkpoint}")
    print(f"loss curve: {Path(args.out) / 'loss_curve.png'}")
    return 0


def _has_prior(path) -> bool:
    from occvo_core.models.tpvformer.checkpoint import read_checkpoint

    return bool(read_checkpoint(path)["config"].get("label_prior"))


def _drive_frames(args, input_size):
    """DriveFrames from --drive-cache or --drive (with its labels), and what the checkpoint records of them."""
    from occvo_core.errors import ConfigError
    from occvo_core.models.drive_training import DriveFrames

    if args.drive is None and args.drive_cache is None:
        for flag in ("drive_scene", "drive_keyframes", "drive_labels"):
            if getattr(args, flag) is not None:
                raise ConfigError(f"--{flag.replace('_', '-')} needs --drive")
        return None, None
    if args.drive_cache is not None and args.drive_cache.is_file():
        frames = DriveFrames.load(args.drive_cache, input_size)
        scene = str(frames.arrays["scene"])
    else:
        from occvo_cli.commands.make_occupancy import keyframe_list
        from occvo_core.datasets.nuscenes_drive import NuScenesDrive

        if args.drive is None:
            raise ConfigError(f"--drive-cache {args.drive_cache} does not exist: give --drive to make it")
        if args.drive_labels is None:
            raise ConfigError("--drive needs --drive-labels DIR (occvo make-occupancy --out) for its voxel targets")
        drive = NuScenesDrive(args.drive, scene=args.drive_scene)
        keyframes = keyframe_list("drive-keyframes", args.drive_keyframes, len(drive))
        frames = DriveFrames.from_drive(drive, args.drive_labels, keyframes, input_size)
        scene = drive.name
        if args.drive_cache is not None:
            frames.save(args.drive_cache)
    span = [frames.keyframes[0], frames.keyframes[-1]]
    return frames, {"train_drive": {"scene": scene, "keyframes": span}, "real_fraction": args.real_fraction}
