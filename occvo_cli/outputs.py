"""What `occvo run` writes beside occvo-out/ as it goes: a rerun view or recording, a Foxglove MCAP file, a ROS 2 bag.
Each is an optional extra, imported only when asked for; each gets every registered frame (step) and the end (finish)."""

from __future__ import annotations

from pathlib import Path

from occvo_core.errors import ConfigError


def add_output_flags(p) -> None:
    p.add_argument(
        "--view", action="store_true", help="show the run live in a rerun viewer (pip install 'occvo[view]')"
    )
    p.add_argument("--rerun", type=Path, metavar="FILE.rrd", help="save the live view as a rerun recording")
    p.add_argument(
        "--mcap",
        type=Path,
        metavar="FILE.mcap",
        help="write the run for Foxglove: poses, path, occupancy and map in Foxglove's schemas "
        "(pip install 'occvo[foxglove]')",
    )
    p.add_argument(
        "--ros2-bag",
        type=Path,
        metavar="DIR",
        help="write the run as a ROS 2 bag (Odometry, /tf, Path, PointCloud2) for ros2 bag play and RViz; DIR must "
        "not exist (pip install 'occvo[ros]')",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --rerun or --mcap file that occvo did not write (default: refused; docs/cli.md)",
    )
    p.add_argument(
        "--map-every", type=int, default=5, help="--view/--rerun/--mcap/--ros2-bag: log the global map every N frames"
    )


def _needs(extra: str, flags: str, exc: ModuleNotFoundError, modules: tuple[str, ...]):
    if (exc.name or "").split(".")[0] not in modules:
        raise exc
    raise ConfigError(f"{flags} needs the {extra} extra: pip install 'occvo[{extra}]'") from None


def check_outputs(args) -> None:
    """Before the run: an existing --rerun or --mcap file that occvo did not write is refused unless --force."""
    from occvo_core.overwrite import check_replaceable

    check_replaceable(args.rerun, "rrd", "--rerun", args.force)
    check_replaceable(args.mcap, "mcap", "--mcap", args.force)


def open_outputs(args):
    """The outputs asked for as one view (step, finish), or None."""
    outputs = []
    if args.view or args.rerun:
        try:
            from occvo_core.viz.rerun_log import RerunView
        except ModuleNotFoundError as exc:
            _needs("view", "--view and --rerun", exc, ("rerun",))
        outputs.append(RerunView.open("occvo", spawn=args.view, save=args.rerun, map_every=args.map_every))
    if args.mcap:
        try:
            from occvo_core.viz.foxglove_log import FoxgloveView
        except ModuleNotFoundError as exc:
            _needs("foxglove", "--mcap", exc, ("foxglove", "mcap"))
        outputs.append(FoxgloveView(mcap=args.mcap, map_every=args.map_every))
    if args.ros2_bag:
        try:
            from occvo_core.viz.ros2_bag import Ros2Bag
        except ModuleNotFoundError as exc:
            _needs("ros", "--ros2-bag", exc, ("rosbags",))
        outputs.append(Ros2Bag(args.ros2_bag, map_every=args.map_every))
    from occvo_core.viz.views import Views

    return Views(outputs) if outputs else None
