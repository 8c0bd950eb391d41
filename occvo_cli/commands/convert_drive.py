"""occvo convert-drive: a nuScenes drive as a ROS 2 recording (MCAP file or bag folder) of its LiDAR occupancy
clouds, ground truth, and six cameras with calibration, which `occvo run --input` reads back."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from occvo_cli.paths import new_path


def add_parser(sub) -> None:
    p = sub.add_parser(
        "convert-drive", help="write a nuScenes drive as a ROS 2 recording (MCAP file or bag folder) for occvo run"
    )
    p.add_argument("--input", type=Path, required=True, help="a nuScenes drive (devkit layout)")
    p.add_argument("--scene", help="the scene to convert (may be left out when the tables hold one)")
    p.add_argument(
        "--out",
        type=new_path,
        required=True,
        help="FILE.mcap (one MCAP file) or a folder (a ROS 2 bag: metadata.yaml + storage); must not exist",
    )
    p.add_argument(
        "--ros-distro",
        choices=("humble", "jazzy"),
        default="jazzy",
        help="the distribution that plays it: the bag version (humble 5, jazzy 8) and message definitions",
    )
    p.add_argument(
        "--storage", choices=("sqlite3", "mcap"), default="sqlite3", help="a bag folder's storage (default sqlite3)"
    )
    p.add_argument("--no-images", action="store_true", help="the occupancy clouds and ground truth only")
    p.add_argument("--json", action="store_true", help="what was written as JSON on stdout")
    p.set_defaults(func=run)


def run(args) -> int:
    from occvo_core.datasets.nuscenes_drive import NuScenesDrive
    from occvo_core.datasets.nuscenes_tables import is_nuscenes_root
    from occvo_core.errors import ConfigError
    from occvo_core.lidar.source import LidarOccupancyScene
    from occvo_core.recording.convert_drive import convert_drive

    if not is_nuscenes_root(args.input):
        raise ConfigError(f"--input {args.input}: not a nuScenes drive (a folder with the devkit's tables)")
    source = LidarOccupancyScene(NuScenesDrive(args.input, scene=args.scene))
    if args.storage == "mcap" and args.out.suffix == ".mcap":
        print("occvo convert-drive: --storage names a bag folder's storage; FILE.mcap is MCAP already", file=sys.stderr)
    count = convert_drive(source, args.out, distro=args.ros_distro, storage=args.storage, images=not args.no_images)
    report = {
        "out": str(args.out),
        "scene": source.drive.name,
        "frames": len(source),
        "messages": count,
        "ros_distro": args.ros_distro,
        "bytes": sum(f.stat().st_size for f in ([args.out] if args.out.is_file() else args.out.rglob("*"))),
    }
    print(json.dumps(report, indent=2) if args.json else f"wrote {args.out}: {len(source)} frames, {count} messages")
    return 0
