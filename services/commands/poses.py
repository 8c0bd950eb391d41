"""occvo poses: print a stream's poses (the trajectory so far, or --follow new ones as they come)."""

from __future__ import annotations

import json
import threading

import numpy as np

from occvo_core.errors import ConfigError
from occvo_schemas import keys
from occvo_schemas.codec import decode
from occvo_schemas.models import PoseEstimate
from occvo_services.commands._common import add_connection, client, progress
from occvo_services.stop_signals import set_on_signal


def _line(p: PoseEstimate, fmt: str) -> str:
    if fmt == "kitti":
        return " ".join(f"{v:.9e}" for row in p.pose[:3] for v in row)
    if fmt == "tum":  # as trajectory.tum: stamp tx ty tz qx qy qz qw
        from scipy.spatial.transform import Rotation

        T = np.asarray(p.pose, np.float64)
        return " ".join(f"{v:.9f}" for v in [p.stamp, *T[:3, 3], *Rotation.from_matrix(T[:3, :3]).as_quat()])
    return json.dumps(
        {
            "stream": p.stream,
            "seq": p.seq,
            "stamp": p.stamp,
            "status": p.status,
            "xyz": [p.pose[0][3], p.pose[1][3], p.pose[2][3]],
            "pose": p.pose,
            "timings_ms": {k: round(v, 3) for k, v in p.timings_ms.items()},
        }
    )


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("poses", help="print poses of a stream")
    add_connection(p)
    p.add_argument("--follow", action="store_true", help="print new poses as they arrive, until Ctrl-C")
    p.add_argument("--count", type=int, default=None, help="with --follow: stop after N poses")
    p.add_argument(
        "--format",
        choices=["json", "kitti", "tum"],
        default="json",
        help="a JSON object, a KITTI row or a TUM row (stamp tx ty tz qx qy qz qw) a pose",
    )
    p.add_argument("--json", action="store_const", const="json", dest="format", help="the same as --format json")
    p.add_argument("--quiet", action="store_true", help="with --follow: no 'following' line on stderr")
    p.set_defaults(func=run)


def run(args) -> int:
    if args.count is not None and args.count < 1:
        raise ConfigError(f"--count must be at least 1, not {args.count}")
    with client(args) as c:
        if not args.follow:
            traj = c.trajectory()
            seqs, poses = traj.seqs.to_numpy(), traj.poses.to_numpy()
            for s, T, st in zip(seqs, poses, traj.stamps.to_numpy()):
                p = PoseEstimate(stream=traj.stream, seq=int(s), stamp=float(st), pose=T.tolist(), status="ok")
                print(_line(p, args.format), flush=True)
            return 0
        done = threading.Event()
        n = [0]

        def on_pose(sample):
            if done.is_set():
                return
            print(_line(decode(sample.payload.to_bytes(), PoseEstimate), args.format), flush=True)
            n[0] += 1
            if args.count is not None and n[0] >= args.count:
                done.set()

        sub = c.session.declare_subscriber(keys.pose(c.stream), on_pose)
        progress(args, f"following {keys.pose(c.stream)}; Ctrl-C stops")
        set_on_signal(done)
        done.wait()
        sub.undeclare()
    return 0
