"""Threads and memory of a registration worker as its streams grow: a worker process opened with max_streams N gets N
streams of a few frames each (occupancy messages straight to it, as the inference worker sends them); within 10 s of
the last frame, before idle_stream_s gives any lane back, its threads (/proc/PID/task) and RSS are read.

    python benchmarks/stream_threads.py                    # 256 streams at max_streams 256, then 64 at the default
    python benchmarks/stream_threads.py --runs 64:64 --frames 3

Prints one line a run: streams, threads, RSS, RSS a stream (RSS over the idle worker's, divided by the streams)."""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from occvo_core.grid import OCC3D_GRID  # noqa: E402
from occvo_core.sim import SyntheticScene  # noqa: E402
from occvo_schemas import keys  # noqa: E402
from occvo_schemas.codec import decode, encode  # noqa: E402
from occvo_schemas.models import OccupancyFrameMsg, PoseEstimate, SparseOccupancy  # noqa: E402
from occvo_services.local import wait_alive  # noqa: E402
from occvo_services.sessions import free_port, open_router, open_session  # noqa: E402
from occvo_services.wire import blocking  # noqa: E402


def _proc_status(pid: int) -> tuple[int, float]:
    """(threads, RSS MB) of a process."""
    fields = dict(line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line)
    return int(fields["Threads"]), int(fields["VmRSS"].split()[0]) / 1024.0


def _frames(n: int) -> list[bytes]:
    """n frames of one synthetic drive, as occupancy messages of stream "{stream}" (encoded once, renamed per stream)."""
    scene = SyntheticScene(seed=1, frames=n)
    out = []
    for i in range(n):
        f = scene[i]
        occ = SparseOccupancy.from_points(f.points, f.labels, OCC3D_GRID)
        out.append(OccupancyFrameMsg(stream="s", seq=i, stamp=float(f.stamp), source="replay", occupancy=occ))
    return out


def run(streams: int, max_streams: int | None, frames: list, timeout: float) -> dict:
    ep = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(ep)
    config = {"max_streams_per_client": max(streams, 16), "idle_stream_s": 60.0, "log_level": "ERROR"}
    if max_streams is not None:
        config["max_streams"] = max_streams
    config_file = Path(tempfile.mkdtemp()) / "registration.json5"
    config_file.write_text(json.dumps(config))
    cmd = [sys.executable, "-m", "occvo_services.registration_worker", "--connect", ep, "--config", str(config_file)]
    proc = subprocess.Popen(cmd, cwd=REPO)
    session = open_session(ep)
    try:
        wait_alive(session, ["registration"], 300.0)
        time.sleep(1.0)
        idle_threads, idle_rss = _proc_status(proc.pid)
        got: dict[str, int] = {}
        lock, done = threading.Lock(), threading.Event()
        want = streams * len(frames)

        def on_pose(sample):
            pose = decode(sample.payload.to_bytes(), PoseEstimate)
            with lock:
                got[pose.stream] = got.get(pose.stream, 0) + (pose.status != "relocalised")
                if sum(got.values()) >= want:
                    done.set()

        sub = session.declare_subscriber(keys.pose("*"), on_pose)
        t0 = time.perf_counter()
        for seq, msg in enumerate(frames):
            for i in range(streams):
                stream = f"car{i}"
                data = encode(msg.model_copy(update={"stream": stream, "seq": seq, "sent_at": time.time()}))
                session.put(keys.occupancy(stream), data, **blocking("occupancy_frame"))
        answered = done.wait(timeout)
        took = time.perf_counter() - t0
        time.sleep(2.0)  # the work after the last poses ends; well within 10 s of the last frame
        threads, rss = _proc_status(proc.pid)
        sub.undeclare()
        return {
            "streams": streams,
            "max_streams": max_streams or 64,
            "poses": sum(got.values()),
            "all_answered": answered,
            "seconds": round(took, 1),
            "threads_idle": idle_threads,
            "threads": threads,
            "rss_mb": round(rss, 1),
            "rss_mb_per_stream": round((rss - idle_rss) / streams, 2),
        }
    finally:
        session.close()
        proc.terminate()
        try:
            proc.wait(60)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        router.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default="256:256,64:", help="streams:max_streams pairs (empty max_streams: the default)")
    ap.add_argument("--frames", type=int, default=2, help="frames a stream")
    ap.add_argument("--timeout", type=float, default=900.0, help="seconds for every pose of a run")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()
    frames = _frames(args.frames)
    results = []
    for pair in args.runs.split(","):
        n, _, cap = pair.partition(":")
        r = run(int(n), int(cap) if cap else None, frames, args.timeout)
        results.append(r)
        print(
            f"streams {r['streams']:4d} max_streams {r['max_streams']:4d}  poses {r['poses']:5d}/"
            f"{r['streams'] * args.frames} in {r['seconds']:6.1f} s  threads {r['threads']:4d} (idle "
            f"{r['threads_idle']})  RSS {r['rss_mb']:7.1f} MB  {r['rss_mb_per_stream']:5.2f} MB a stream",
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))
    return 0 if all(r["all_answered"] for r in results) else 1


if __name__ == "__main__":
    np.seterr(all="ignore")
    sys.exit(main())
