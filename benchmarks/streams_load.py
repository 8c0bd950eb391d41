"""Many streams at a camera rate on one machine: does the service keep up, and does a backlog grow?

    python benchmarks/streams_load.py --streams 8 --rate 2 --minutes 5            # the full measurement
    python benchmarks/streams_load.py --streams 8 --rate 2 --minutes 5 --working-radius 120   # as deployed
    python benchmarks/streams_load.py --streams 8 --minutes 5 --working-radius 120 --registration-workers 2  # 2 shards
    python benchmarks/streams_load.py --streams 12 --minutes 5 --working-radius 120 --registration-workers 2 \
        --placement members                                                        # 2 workers, least loaded first
    python benchmarks/streams_load.py --streams 2 4 6 8 --minutes 1               # a sweep: one run per count
    python benchmarks/streams_load.py --streams 8 --policy latest --minutes 1     # what dropping the oldest does
    python benchmarks/streams_load.py --streams 8 --minutes 5 --working-radius 120 --registration-workers 2 \
        --neighbour-load 0.35                                                      # on a host shared with a busy neighbour

Router in this process, the three workers as subprocesses (occvo_services.local.LocalService). Each stream replays its own
synthetic scene (seed = stream number) open loop at --rate, as a live camera would: frame i leaves at t0 + i / rate
whatever came back, through the product's client (OccVOClient: it sends again what a full queue turned away). Scenes are rendered once before the run (in --render-jobs processes, niced) and cached as voxel
indices in --cache-dir, so the client only builds and sends messages; its send cost per frame is measured and printed.

Per minute and stream: frames sent and poses received; pose latency p50/p99 (client send to pose arrival); the
registration queue depth (WorkerHealth.queue_depth from occvo/@workers/<id>/stats, sampled every --sample-s); frames in
flight (sent - received). Backlog: least-squares slopes of queue depth, frames in flight and latency over time, and the
ratio of the last minute's latency p99 to the first minute's. Prints a table and one JSON line per run.
"Keeps up" = every frame sent on time and answered, poses at >= 95% of the offered rate in the last bucket, frames in
flight growing by less than one per stream per minute, and the median latency of the last bucket under twice the first's.

Beyond capacity, `lossless` answers a frame its stream's queue cannot take with stream_full and the client sends it
again (docs/service.md, "Lossless under overload"): frames wait at the client and latency grows; none is lost.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

from _common import start_neighbours
from _streams_report import print_run
from _streams_run import run_load
from _streams_scenes import load_scenes


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument(
        "--streams", type=int, nargs="+", default=[8], help="stream counts; several = a sweep, one run each"
    )
    ap.add_argument("--rate", type=float, default=2.0, help="frames per second per stream")
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--policy", choices=["lossless", "latest"], default="lossless")
    ap.add_argument("--queue-size", type=int, default=4)
    ap.add_argument("--no-store", action="store_true", help="map service in memory (default: a SQLite store per run)")
    ap.add_argument(
        "--working-radius",
        type=float,
        default=0.0,
        help="registration worker with a SQLite store and "
        "eviction beyond this many m, as deploy/registration_worker.json5 (120); 0: in memory, maps grow",
    )
    ap.add_argument(
        "--registration-workers",
        type=int,
        default=1,
        help="registration workers sharing the streams (shards, as `count: N` in occvo up)",
    )
    ap.add_argument(
        "--placement",
        choices=["shards", "members"],
        default="shards",
        help="how the registration workers share the streams: shards (by the hash of the stream id, `count: N` in "
        "occvo up) or members (the least-loaded live worker takes a new stream, under leases in the store)",
    )
    ap.add_argument(
        "--after-pose-nice",
        type=int,
        default=None,
        help="niceness of the registration worker's work after a pose (0: the lanes'; default: the worker's, 10)",
    )
    ap.add_argument(
        "--snapshot-max-share",
        type=float,
        default=None,
        help="the registration worker's snapshot_max_share (default: the worker's, 0.02)",
    )
    ap.add_argument(
        "--store-sync",
        choices=["full", "normal"],
        default=None,
        help="the registration worker's store_sync (default: the worker's, full)",
    )
    ap.add_argument(
        "--neighbour-load",
        type=float,
        default=0.0,
        help="a busy process per core, busy this share of "
        "every 100 ms (0.35: a host stealing about a third of the cores)",
    )
    ap.add_argument("--sample-s", type=float, default=3.0, help="seconds between worker stats samples")
    ap.add_argument(
        "--bucket-s",
        type=float,
        default=None,
        help="report bucket (default 60 s; a third of the run when shorter than 3 min)",
    )
    ap.add_argument(
        "--drain-s", type=float, default=60.0, help="wait this long after the last send for outstanding poses"
    )
    ap.add_argument("--cache-dir", default=str(Path(tempfile.gettempdir()) / "occvo-streams-cache"))
    ap.add_argument("--render-jobs", type=int, default=2)
    ap.add_argument("--log-dir", help="keep the workers' logs and the map store here (default: a temporary folder)")
    ap.add_argument("--output", help="write all runs as JSON here")
    args = ap.parse_args(argv)
    if args.placement == "members" and args.working_radius <= 0:
        ap.error("--placement members needs the registration store: give --working-radius (as deployed, 120)")
    bucket_s = args.bucket_s or (60.0 if args.minutes >= 3 else args.minutes * 20.0)
    total = int(round(args.minutes * 60 * args.rate))
    scenes = load_scenes(list(range(max(args.streams))), total, args.rate, Path(args.cache_dir), args.render_jobs)
    neighbours = start_neighbours(args.neighbour_load)  # after rendering: they load the run, not the preparation
    results = []
    for n in args.streams:
        with tempfile.TemporaryDirectory(prefix="occvo-load-") as tmp:
            log_dir = Path(args.log_dir) / f"{n}-streams" if args.log_dir else Path(tmp)
            log_dir.mkdir(parents=True, exist_ok=True)
            r = run_load(
                n,
                args.rate,
                args.minutes,
                args.policy,
                args.queue_size,
                scenes,
                not args.no_store,
                args.sample_s,
                bucket_s,
                args.drain_s,
                log_dir,
                args.working_radius,
                args.registration_workers,
                args.after_pose_nice,
                args.snapshot_max_share,
                args.store_sync,
                args.placement,
            )
        r["neighbour_load"] = args.neighbour_load
        results.append(r)
        print_run(r, bucket_s)
        print(
            json.dumps(
                {k: v for k, v in r.items() if k != "buckets"}
                | {
                    "buckets": [
                        {k: v for k, v in b.items() if k != "per_stream"} | {"per_stream": b["per_stream"]}
                        for b in r["buckets"]
                    ]
                }
            ),
            flush=True,
        )
    for proc in neighbours:
        proc.terminate()
    if len(results) > 1:
        ok = [r["streams"] for r in results if r["keeps_up"]]
        print(
            f"\nhighest stream count that keeps up at {args.rate:g} Hz ({args.policy}): {max(ok) if ok else 'none of'} "
            f"{'' if ok else args.streams}"
        )
    if args.output:
        Path(args.output).write_text(json.dumps(results, indent=2, default=float))
    return 0


if __name__ == "__main__":
    sys.exit(main())
