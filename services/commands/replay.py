"""occvo replay: publish a scene's frames to a stream, at a rate or as fast as the pipeline takes (lossless)."""

from __future__ import annotations

import sys
import time

import numpy as np

from occvo_services.client import PENDING_CODES, OccVOClient, ServiceError
from occvo_services.commands._common import add_connection, add_json, client, emit


def load_scene(
    spec: str, frames: int | None = None, scene: str | None = None, mask: str = "camera", occupancy: str | None = None
):
    """A scene folder (OCC-VO release or Occ3D layout), an Occ3D-nuScenes root with `scene`, a nuScenes drive with
    occupancy "lidar", or `synthetic:<seed>`."""
    if spec.startswith("synthetic:"):
        from occvo_core.errors import ConfigError
        from occvo_core.sim import SyntheticScene

        try:
            seed = int(spec.split(":", 1)[1])
        except ValueError:
            raise ConfigError(f"synthetic scene spec is synthetic:<seed>, got {spec!r}") from None
        return SyntheticScene(seed=seed, frames=frames or 40)
    from occvo_core.datasets import open_scene

    return open_scene(spec, scene=scene, mask=mask, occupancy=occupancy)


def replay(
    client: OccVOClient,
    scene,
    rate_hz: float = 0.0,
    window: int = 4,
    frames: int | None = None,
    timeout: float = 120.0,
    progress=None,
) -> dict:
    """Publish frames 0..n-1 as one trajectory, keeping at most `window` frames in flight (application-level
    backpressure: the next frame goes out when an earlier pose or error came back). Frames in flight when the
    registration worker restarts are sent again by the client (OccVOClient.resend_after, its liveliness token), so a
    replay survives a crashed worker that comes back with its store. Returns a summary."""
    n = len(scene) if frames is None else min(frames, len(scene))
    client.reset()
    t0 = time.perf_counter()
    sent_at = []
    for i in range(n):
        frame = scene[i]
        if rate_hz > 0:
            delay = t0 + i / rate_hz - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        if not _settled_within(client, i - window + 1, timeout):
            raise ServiceError(f"pipeline stalled: no pose for {timeout} s with {window} frames in flight")
        sent_at.append(time.perf_counter())
        client.publish(frame)
        if progress:
            progress(i, n)
    _settled_within(client, n, timeout)  # whether or not all came, the summary says how many did
    elapsed = time.perf_counter() - t0
    poses = dict(client.poses)
    return {
        "stream": client.stream,
        "frames": n,
        "poses": len(poses),
        "errors": len(client.errors),
        "resends": client.resends,
        "seconds": elapsed,
        "fps": len(poses) / elapsed if elapsed > 0 else 0.0,
        "trajectory": np.array([poses[s].matrix() for s in sorted(poses)]) if poses else np.zeros((0, 4, 4)),
        "pose_msgs": poses,
        "sent_at": sent_at,  # time.perf_counter() each frame left, by seq (client.arrived: when its pose came)
    }


def _settled(client: OccVOClient) -> int:
    """Frames answered: a pose, or an error that is the frame's end (a missing seq, a held jump, a write the store
    refused are not: the client sends the frame again)."""
    failed = {
        e.seq for e in client.errors if e.seq is not None and e.seq not in client.poses and e.code not in PENDING_CODES
    }
    return len(client.poses) + len(failed)


def _settled_within(client: OccVOClient, count: int, timeout: float) -> bool:
    """Whether `count` frames are answered within `timeout` s."""
    deadline = time.monotonic() + timeout
    with client._cv:
        while _settled(client) < count:
            if not client._cv.wait(max(0.0, deadline - time.monotonic())) and time.monotonic() > deadline:
                return False
    return True


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("replay", help="publish a scene (folder or synthetic:<seed>) to the running service")
    p.add_argument(
        "scene",
        nargs="?",
        help="scene folder (OCC-VO release or Occ3D layout), Occ3D-nuScenes root with "
        "--scene, or synthetic:<seed>; none with --nuscenes",
    )
    p.add_argument(
        "--nuscenes",
        metavar="DATAROOT",
        help="publish a nuScenes scene's six keyframe camera images, with "
        "their calibration and timestamps, for the model source (--version, --scene)",
    )
    p.add_argument(
        "--version", help="--nuscenes: the tables' folder (default: the one folder of tables, e.g. v1.0-mini)"
    )
    p.add_argument(
        "--scene",
        dest="scene_name",
        help="the scene of an Occ3D-nuScenes root (annotations.json + gts/) or of --nuscenes (default: its only scene)",
    )
    p.add_argument("--mask", choices=("camera", "lidar", "none"), default="camera", help="Occ3D input: visibility mask")
    p.add_argument(
        "--occupancy", choices=("lidar",), help="a nuScenes drive as SCENE: occupancy from each keyframe's LiDAR sweep"
    )
    add_connection(p)
    p.add_argument("--rate", type=float, default=0.0, help="frames per second; 0 = as fast as the pipeline takes")
    p.add_argument("--window", type=int, default=4, help="frames in flight at most (lossless replay)")
    p.add_argument("--frames", type=int, default=None, help="replay only the first N frames")
    p.add_argument(
        "--timeout", type=float, default=120.0, help="seconds to wait for the poses after the last frame (default 120)"
    )
    p.add_argument(
        "--resend-after",
        type=float,
        default=5.0,
        help="send unanswered frames again after this many seconds without an answer (also when the "
        "registration worker comes back); 0 = never",
    )
    p.add_argument(
        "--out",
        "--output",
        dest="out",
        help="write the received trajectory here: TUM (stamped with the frames' stamps) when the name ends in .tum "
        "or with --format tum, else KITTI (--output: the old name)",
    )
    p.add_argument("--format", choices=("kitti", "tum"), help="--out's format (default: by its name)")
    p.add_argument("--tum", metavar="FILE", help="the same as --out FILE --format tum (the old spelling)")
    p.add_argument(
        "--force",
        action="store_true",
        help="replace an existing --out file that occvo did not write (default: refused; docs/cli.md)",
    )
    add_json(p, "the summary")
    p.add_argument("--quiet", action="store_true", help="no progress bar and no error events on stderr")
    p.set_defaults(func=run)


def run(args) -> int:
    from tqdm import tqdm

    from occvo_core.errors import ConfigError

    for name, value, low in (("--frames", args.frames, 1), ("--window", args.window, 1)):
        if value is not None and value < low:
            raise ConfigError(f"{name} must be at least {low}, not {value}")
    if args.rate < 0 or args.timeout <= 0:
        raise ConfigError("--rate must be 0 or more and --timeout more than 0")
    from occvo_core.overwrite import check_replaceable

    check_replaceable(args.out, "trajectory", "--out", args.force)  # before the drive, not after it
    check_replaceable(args.tum, "trajectory", "--tum", args.force)
    if args.nuscenes:
        from occvo_services.nuscenes_source import NuScenesCameraFrames

        scene = NuScenesCameraFrames(args.nuscenes, args.version, args.scene_name)
    elif args.scene is None:
        raise ConfigError("replay needs a scene (folder or synthetic:<seed>) or --nuscenes DATAROOT")
    else:
        scene = load_scene(args.scene, args.frames, args.scene_name, args.mask, args.occupancy)
    with client(args, resend_after=args.resend_after or None) as c:
        c.wait_for_workers(timeout=args.timeout)
        n = len(scene) if args.frames is None else min(args.frames, len(scene))
        with tqdm(total=n, desc=f"replay {c.stream}", unit="frame", disable=args.quiet, file=sys.stderr) as bar:
            out = replay(
                c, scene, args.rate, args.window, args.frames, args.timeout, progress=lambda i, n: bar.update()
            )
        errors = list(c.errors)
    _write_trajectory(args, out)
    if not args.quiet:
        for e in errors:
            print(f"occvo replay: frame {e.seq}: {e.code}: {e.message}", file=sys.stderr)
    record = {k: v for k, v in out.items() if k not in ("trajectory", "pose_msgs")}
    emit(
        args,
        record,
        f"{record['poses']} poses of {record['frames']} frames of stream {record['stream']} in "
        f"{record['seconds']:.1f} s ({record['fps']:.1f} frames/s), {record['errors']} errors, "
        f"{record['resends']} resends",
    )
    if out["poses"] != out["frames"]:
        raise ServiceError(
            f"{out['frames'] - out['poses']} of {out['frames']} frames got no pose (see the error "
            "events above or the registration worker's log)"
        )
    return 0


def _write_trajectory(args, out: dict) -> None:
    from occvo_core.trajectory import write_kitti, write_tum

    wanted = [(args.out, args.format or ("tum" if str(args.out).endswith(".tum") else "kitti"))] if args.out else []
    wanted += [(args.tum, "tum")] if args.tum else []
    for path, fmt in wanted:
        if not len(out["trajectory"]):
            continue
        if fmt == "tum":
            msgs = out["pose_msgs"]
            write_tum(path, out["trajectory"], np.array([msgs[s].stamp for s in sorted(msgs)]))
        else:
            write_kitti(path, out["trajectory"])
