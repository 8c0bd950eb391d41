"""Scale-out: N streams through one, then two registration workers (placement "members", each pinned to one core with
taskset) on a PostgreSQL store, then a kill -9 of one of two workers mid-drive.

    python benchmarks/scale_out.py [--streams 8] [--frames 40] [--store-url postgresql://...] [--output F.json]

Every stream is a lossless replay (window 4) started at once, so the workers are saturated; frames/s = the poses
that arrived while every stream was still driving, over that time (once a stream's drive is over, a worker can run
out of work: the drive's end measures how the streams happened to be split, not a worker's capacity); the whole
drive's frames/s is reported beside it. 1 and 2 workers alternate --repeats times; scaling is the median of the
pairs' ratios. The failover run drives the streams at the rate that saturates one worker (its frames/s of the
first run, shared by the streams), so the survivor can carry them all. Keys: scaling (frames/s with 2 workers over 1), failover_s_p50 / failover_s_max (the kill to the
first pose of each moved stream), poses_lost (frames without a pose, every run), poses_bit_identical (every pose of
every run equal to offline OccVO's), store. Without --store-url a throwaway PostgreSQL cluster is started
(occvo_services.store.pg_local, Debian's postgresql-15)."""

from __future__ import annotations

import argparse
import collections
import json
import os
import threading
import time
from pathlib import Path

import numpy as np

from occvo_core import OccVO
from occvo_core.datasets.occvo_release import OccVOReleaseScene
from occvo_core.sim import SyntheticScene
from occvo_services.client import OccVOClient
from occvo_services.commands.replay import replay
from occvo_services.local import LocalService

DATA = Path(__file__).resolve().parents[2] / "shared/data/occvo-sample/occupancy"


def scenes(n: int, frames: int) -> dict[str, list]:
    """n streams: the real scenes where they are, synthetic drives for the rest."""
    out = {}
    for name in ("scene-0101", "scene-0268"):
        if len(out) < n and (DATA / name).is_dir():
            scene = OccVOReleaseScene(DATA / name)
            out[name.replace("scene-", "real")] = [scene[i] for i in range(min(frames, len(scene)))]
    seed = 60
    while len(out) < n:
        scene = SyntheticScene(seed=seed, frames=frames)
        out[f"town{seed}"] = [scene[i] for i in range(frames)]
        seed += 1
    return out


def offline(drives: dict[str, list]) -> dict[str, np.ndarray]:
    out = {}
    for stream, frames in drives.items():
        vo = OccVO()
        out[stream] = np.array([vo.step(f).pose for f in frames])
    return out


def service(workers: int, store_url: str) -> LocalService:
    pin = {"registration": "0"} if workers == 1 else {f"registration-{i}": str(i) for i in range(workers)}
    args = ["--store-url", store_url, "--lease-s", "5"]  # pinned to one core: its kernels run on one thread
    return LocalService(
        quiet=True, registration_shards=workers, placement="members", pin=pin, worker_args={"registration": args}
    )


def saturated_fps(t0: float, runs: dict) -> float:
    """Poses a second while every stream was driving: from the start to the first stream's last pose."""
    t_end = min(max(s["arrived"].values()) for s in runs.values())
    poses = sum(1 for s in runs.values() for t in s["arrived"].values() if t <= t_end)
    return poses / (t_end - t0)


def drive_all(svc: LocalService, drives: dict, rate_hz: float = 0.0, on_started=None) -> tuple[float, dict]:
    """Every stream replayed at once (rate_hz 0: as fast as answers come, window 4); (start time, {stream: replay
    summary with the client's arrival times}); the summaries' "wall_s" is the whole drive's time."""
    out: dict = {}

    def one(stream: str, frames: list) -> None:
        with OccVOClient(svc.endpoint, stream, timeout=120, resend_after=5.0) as c:
            summary = replay(c, frames, rate_hz=rate_hz, window=4, timeout=120)
            summary["arrived"] = dict(c.arrived)
            out[stream] = summary

    threads = [threading.Thread(target=one, args=item) for item in drives.items()]
    t0 = time.perf_counter()
    for t in threads:
        t.start()
    if on_started is not None:
        on_started()
    for t in threads:
        t.join()
    for summary in out.values():
        summary["wall_s"] = time.perf_counter() - t0
    return t0, out


def streams_per_worker(store_url: str, drives: dict) -> list[int]:
    from occvo_services.store.factory import open_store

    store = open_store(store_url)
    try:
        return sorted(collections.Counter(store.owner_of(s) for s in drives).values())
    finally:
        store.close()


def check(runs: dict, want: dict) -> tuple[int, bool]:
    lost = sum(s["frames"] - s["poses"] for s in runs.values())
    same = all(np.array_equal(runs[k]["trajectory"], want[k]) for k in want if k in runs)
    return lost, same and set(runs) == set(want)


def failover(store_url: str, drives: dict, want: dict, rate_hz: float, kill_after_s: float) -> dict:
    """Two workers, every stream at rate_hz (together the rate that saturates one worker); registration-0 killed (-9)
    kill_after_s into the drive; how long each of its streams waits for its next pose."""
    from occvo_services.store.factory import open_store

    with service(2, store_url) as svc:
        victim = f"registration-0-{os.getpid()}"  # LocalService's worker ids: <name>-<pid of the process starting it>
        killed: dict = {}

        def kill() -> None:
            time.sleep(kill_after_s)
            store = open_store(store_url)
            killed["streams"] = [s for s in drives if store.owner_of(s) == victim]
            store.close()
            svc.procs["registration-0"].kill()
            killed["at"] = time.perf_counter()

        _, runs = drive_all(svc, drives, rate_hz, on_started=lambda: threading.Thread(target=kill).start())
    waits = [min(t for t in runs[s]["arrived"].values() if t > killed["at"]) - killed["at"] for s in killed["streams"]]
    lost, same = check(runs, want)
    return {"moved_streams": killed["streams"], "failover_s": waits, "poses_lost": lost, "bit_identical": same}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--streams", type=int, default=8, help="streams driven at once")
    ap.add_argument("--frames", type=int, default=40, help="frames a stream")
    ap.add_argument("--store-url", help="a PostgreSQL database to use (default: a throwaway local cluster)")
    ap.add_argument("--kill-after-s", type=float, default=6.0, help="failover run: seconds into the drive")
    ap.add_argument("--repeats", type=int, default=3, help="pairs of 1- and 2-worker runs (scaling: their median)")
    ap.add_argument("--output", help="write the figures as JSON")
    args = ap.parse_args()
    drives = scenes(args.streams, args.frames)
    want = offline(drives)
    cluster = None
    if args.store_url is None:
        from occvo_services.store.pg_local import PgCluster, missing

        if missing():
            raise SystemExit(missing())
        cluster = PgCluster()
    try:
        url = (lambda: args.store_url) if args.store_url else cluster.new_database
        fps, whole, lost, same = {1: [], 2: []}, {1: [], 2: []}, 0, True
        for _ in range(args.repeats):
            for workers in (1, 2):
                store_url = url()
                with service(workers, store_url) as svc:
                    t0, runs = drive_all(svc, drives)
                    split = streams_per_worker(store_url, drives)
                fps[workers].append(saturated_fps(t0, runs))
                whole[workers].append(sum(s["poses"] for s in runs.values()) / max(s["wall_s"] for s in runs.values()))
                run_lost, run_same = check(runs, want)
                lost, same = lost + run_lost, same and run_same
                print(
                    f"{workers} worker(s): {fps[workers][-1]:.1f} frames/s while every stream drives, "
                    f"{whole[workers][-1]:.1f} over the whole drive, {run_lost} poses lost, bit-identical {run_same}, "
                    f"streams a worker {split}"
                )
        ratios = [b / a for a, b in zip(fps[1], fps[2])]
        fail = failover(url(), drives, want, float(np.median(fps[1])) / len(drives), args.kill_after_s)
        print(f"failover: {len(fail['moved_streams'])} streams moved, first poses after {fail['failover_s']} s")
    finally:
        if cluster is not None:
            cluster.close()
    waits = fail["failover_s"] or [float("nan")]
    out = {
        "streams": len(drives),
        "streams_per_worker": split,
        "frames_per_s": {str(k): round(float(np.median(v)), 2) for k, v in fps.items()},
        "frames_per_s_whole_drive": {str(k): round(float(np.median(v)), 2) for k, v in whole.items()},
        "scaling": round(float(np.median(ratios)), 3),
        "scaling_runs": [round(r, 3) for r in ratios],
        "scaling_whole_drive": round(float(np.median([b / a for a, b in zip(whole[1], whole[2])])), 3),
        "failover_s_p50": round(float(np.median(waits)), 3),
        "failover_s_max": round(float(np.max(waits)), 3),
        "poses_lost": lost + fail["poses_lost"],
        "poses_bit_identical": same and fail["bit_identical"],
        "store": "postgresql",
    }
    print(json.dumps(out))
    if args.output:
        Path(args.output).write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
