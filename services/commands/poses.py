"""occvo poses: print a stream's poses (the trajectory so far, or --follow new ones as they come)."""

from __future__ import annotations

import json
import signal
import sys
import threading

from schemas import keys
from schemas.codec import decode
from schemas.models import PoseEstimate
from services.client import OccVOClient
from services.commands._common import add_connection, endpoint


def _line(p: PoseEstimate, fmt: str) -> str:
    if fmt == "kitti":
        return " ".join(f"{v:.9e}" for row in p.pose[:3] for v in row)
    return json.dumps({"stream": p.stream, "seq": p.seq, "stamp": p.stamp, "status": p.status,
                       "xyz": [p.pose[0][3], p.pose[1][3], p.pose[2][3]], "pose": p.pose,
                       "timings_ms": {k: round(v, 3) for k, v in p.timings_ms.items()}})


def add_parser(subparsers) -> None:
    p = subparsers.add_parser("poses", help="print poses of a stream")
    add_connection(p)
    p.add_argument("--follow", action="store_true", help="print new poses as they arrive, until Ctrl-C")
    p.add_argument("--count", type=int, default=None, help="with --follow: stop after N poses")
    p.add_argument("--format", choices=["json", "kitti"], default="json")
    p.set_defaults(func=run)


def run(args) -> int:
    with OccVOClient(endpoint(args), stream=args.stream) as client:
        if not args.follow:
            traj = client.trajectory()
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

        sub = client.session.declare_subscriber(keys.pose(args.stream), on_pose)
        print(json.dumps({"event": "following", "key": keys.pose(args.stream)}), file=sys.stderr, flush=True)
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda *_: done.set())
        done.wait()
        sub.undeclare()
    return 0
