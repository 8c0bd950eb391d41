"""occvo train-occ: train TPV-Former on synthetic scenes (images rendered from the true occupancy) for a time budget."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from occvo_cli.paths import out_dir


def add_parser(sub) -> None:
    p = sub.add_parser("train-occ", help="train the TPV-Former occupancy network on synthetic scenes")
    p.add_argument("--preset", default="tiny", help="network preset: tiny or paper")
    p.add_argument("--minutes", type=float, required=True, help="wall-clock training budget")
    p.add_argument(
        "--out", type=out_dir, required=True, help="output folder: checkpoint.pt, loss_curve.png, train_log.json"
    )
    p.add_argument("--seeds", type=int, nargs="+", default=list(range(20)), help="synthetic training scene seeds")
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
