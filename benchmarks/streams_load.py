"""Many streams at a camera rate on one machine: does the service keep up, and does a backlog grow?

    python benchmarks/streams_load.py --streams 8 --rate 2 --minutes 5            # the full measurement
    python benchmarks/streams_load.py --streams 8 --rate 2 --minutes 5 --working-radius 120   # as deployed
    python benchmarks/streams_load.py --streams 8 --minutes 5 --working-radius 120 --registration-workers 2  # 2 shards
    python benchmarks/streams_load.py --streams 2 4 6 8 --minutes 1               # a sweep: one run per count
    python benchmarks/streams_load.py --streams 8 --policy latest --minutes 1     # what dropping the oldest does
    python benchmarks/streams_load.py --streams 8 --minutes 5 --working-radius 120 --registration-workers 2 \
        --neighbour-load 0.35                                                      # on a host shared with a busy neighbour

Router in this process, the three workers as subprocesses (occvo_services.local.LocalService). Each stream replays its own
synthetic scene (seed = stream number) open loop at --rate, as a live camera would: frame i leaves at t0 + i / rate
whatever came back. Scenes are rendered once before the run (in --render-jobs processes, niced) and cached as voxel
indices in --cache-dir, so the client only builds and sends messages; its send cost per frame is measured and printed.

Per minute and stream: frames sent and poses received; pose latency p50/p99 (client send to pose arrival); the
registration queue depth (WorkerHealth.queue_depth from occvo/@workers/<id>/stats, sampled every --sample-s); frames in
flight (sent - received). Backlog: least-squares slopes of queue depth, frames in flight and latency over time, and the
ratio of the last minute's latency p99 to the first minute's. Prints a table and one JSON line per run.
"Keeps up" = every frame sent on time and answered, poses at >= 95% of the offered rate in the last bucket, frames in
flight growing by less than one per stream per minute, and the median latency of the last bucket under twice the first's.

Beyond capacity, `lossless` is not lossless end to end: a worker whose queues are full blocks its Zenoh callback, and
Zenoh closes a link blocked longer than transport/link/tx/queue/congestion_control/block/wait_before_close (5 s by
default), losing what was buffered on it; the registration worker then reports missing_seq (docs/service.md).
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import sys
import tempfile
import threading
import time
import warnings
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
warnings.filterwarnings("ignore", category=RuntimeWarning)

from occvo_core.grid import OCC3D_GRID  # noqa: E402
from occvo_schemas import keys  # noqa: E402
from occvo_schemas.codec import CodecError, decode, encode  # noqa: E402
from occvo_schemas.models import (  # noqa: E402
    Array,
    CameraFrame,
    ErrorEvent,
    GridSpecModel,
    PoseEstimate,
    SparseOccupancy,
    WorkerHealth,
)
from occvo_services.local import LocalService  # noqa: E402
from occvo_services.sessions import open_session  # noqa: E402

# ---------------------------------------------------------------- scenes, rendered once


def _render(args: tuple[int, int, float, str]) -> str:
    """Render one synthetic scene to an npz of voxel indices (synthetic frames lie on the grid: nothing is lost)."""
    seed, frames, rate, path = args
    os.nice(10)  # leave the cores to whatever else runs on the machine
    from occvo_core.sim import SyntheticScene

    scene = SyntheticScene(seed=seed, frames=frames, rate_hz=rate)
    idx, labels, counts, stamps = [], [], [], []
    for i in range(frames):
        f = scene[i]
        idx.append(OCC3D_GRID.indices_of(f.points).astype(np.uint8))
        labels.append(f.labels.astype(np.uint8))
        counts.append(len(f.labels))
        stamps.append(f.stamp)
        scene._frames.clear()  # the scene caches frames; we keep only the compact copy
    tmp = path + ".tmp.npz"
    np.savez(
        tmp, idx=np.concatenate(idx), labels=np.concatenate(labels), counts=np.array(counts), stamps=np.array(stamps)
    )
    os.replace(tmp, path)
    return path


def _cached(cache_dir: Path, seed: int, frames: int, rate: float) -> Path:
    """The shortest cached render of this seed with at least `frames` frames (its first frames are a drive too)."""
    have = []
    for p in cache_dir.glob(f"synthetic-{seed}-*f-{rate:g}hz.npz"):
        try:
            n = int(p.name.split("-")[2][:-1])
        except ValueError:
            continue
        if n >= frames:
            have.append((n, p))
    return min(have)[1] if have else cache_dir / f"synthetic-{seed}-{frames}f-{rate:g}hz.npz"


def load_scenes(
    seeds: list[int], frames: int, rate: float, cache_dir: Path, jobs: int
) -> dict[int, list[SparseOccupancy]]:
    cache_dir.mkdir(parents=True, exist_ok=True)
    paths = {s: _cached(cache_dir, s, frames, rate) for s in seeds}
    todo = [(s, frames, rate, str(p)) for s, p in paths.items() if not p.exists()]
    if todo:
        t0 = time.perf_counter()
        print(f"rendering {len(todo)} scenes of {frames} frames into {cache_dir} ({jobs} processes)...", flush=True)
        with ProcessPoolExecutor(jobs) as pool:
            list(pool.map(_render, todo))
        print(f"rendered in {time.perf_counter() - t0:.0f} s", flush=True)
    grid = GridSpecModel.from_grid(OCC3D_GRID)
    out = {}
    for s, p in paths.items():
        with np.load(p) as z:  # an npz reads an array on every z[...]: once each
            idx, labels, ends = z["idx"], z["labels"], np.cumsum(z["counts"])
        out[s] = [
            SparseOccupancy(grid=grid, voxels=Array.from_numpy(idx[a:b]), labels=Array.from_numpy(labels[a:b]))
            for a, b in list(zip(np.r_[0, ends[:-1]], ends))[:frames]
        ]
    return out


# ---------------------------------------------------------------- one run


class Stream:
    """One stream's sender: frame i leaves at t0 + (i + offset) / rate, open loop."""

    def __init__(self, name: str, frames: list[SparseOccupancy], offset: float):
        self.name, self.frames, self.offset = name, frames, offset
        self.due = np.zeros(len(frames))  # wall clock the frame is due (a camera would capture it then)
        self.sent_at = np.full(len(frames), np.nan)  # wall clock at send (the message's sent_at)
        self.lag = np.full(len(frames), np.nan)  # send time - schedule, s
        self.build_ms = np.full(len(frames), np.nan)  # message build + encode
        self.put_ms = np.full(len(frames), np.nan)  # Zenoh put (blocks under lossless backpressure)
        self.recv_at: dict[int, float] = {}
        self.timings: dict[int, dict[str, float]] = {}  # seq -> the pose's timings_ms (where its time went)
        self.last_sent = -1
        self.errors: dict[str, int] = {}

    def on_pose(self, sample) -> None:
        t = time.time()
        try:
            pose = decode(sample.payload.to_bytes(), PoseEstimate)
        except CodecError:
            return
        self.recv_at.setdefault(pose.seq, t)
        self.timings.setdefault(pose.seq, pose.timings_ms)

    def newest_back(self) -> int:
        return max(self.recv_at, default=-1)

    def send_all(self, pub, t0: float, rate: float, stop: threading.Event) -> None:
        """Until every frame is sent or `stop` (the end of the window): under lossless backpressure a put blocks,
        the schedule slips (send lag) and frames due after the window are never sent."""
        self.due = t0 + (np.arange(len(self.frames)) + self.offset) / rate
        for i, occ in enumerate(self.frames):
            due = self.due[i]
            while not stop.is_set() and time.time() < due:
                time.sleep(min(0.05, max(0.0, due - time.time())))
            if stop.is_set():
                return
            a = time.perf_counter()
            now = time.time()
            data = encode(CameraFrame(stream=self.name, seq=i, stamp=i / rate, gt_occupancy=occ, sent_at=now))
            b = time.perf_counter()
            pub.put(data)
            self.put_ms[i] = (time.perf_counter() - b) * 1000.0
            self.build_ms[i] = (b - a) * 1000.0
            self.sent_at[i], self.lag[i] = now, now - due
            self.last_sent = i


def _stage_medians(timings: list[dict[str, float]]) -> dict[str, float]:
    """Median ms of each stage over some poses' timings_ms, largest first (where the slowest frames' time went)."""
    names = {k for t in timings for k in t}
    med = {k: float(np.median([t.get(k, 0.0) for t in timings])) for k in names}
    return dict(sorted(med.items(), key=lambda kv: -kv[1]))


def _pct(a, q) -> float | None:
    a = np.asarray([x for x in a if x == x])
    return float(np.percentile(a, q)) if len(a) else None


def _slope(t, y) -> float | None:
    """Least-squares slope of y per minute of t (seconds)."""
    t, y = np.asarray(t, float), np.asarray(y, float)
    return float(np.polyfit(t / 60.0, y, 1)[0]) if len(t) >= 3 and np.ptp(t) > 0 else None


def _neighbour(duty: float) -> None:
    """A noisy neighbour on one core: busy `duty` of every 100 ms (--neighbour-load; a stand-in for host steal)."""
    while True:
        t = time.perf_counter()
        while time.perf_counter() - t < duty * 0.1:
            pass
        time.sleep((1.0 - duty) * 0.1)


def start_neighbours(duty: float) -> list:
    """One noisy neighbour process a core (daemons; terminate() them when done). None for duty 0."""
    if duty <= 0:
        return []
    ctx = multiprocessing.get_context("spawn")
    neighbours = [ctx.Process(target=_neighbour, args=(duty,), daemon=True) for _ in range(os.cpu_count() or 1)]
    for proc in neighbours:
        proc.start()
    return neighbours


def run_load(
    n: int,
    rate: float,
    minutes: float,
    policy: str,
    queue_size: int,
    scenes: dict,
    store: bool,
    sample_s: float,
    bucket_s: float,
    drain_s: float,
    log_dir: Path,
    working_radius: float = 0.0,
    registration_workers: int = 1,
    after_pose_nice: int | None = None,
    snapshot_max_share: float | None = None,
    store_sync: str | None = None,
) -> dict:
    import psutil

    total = int(round(minutes * 60 * rate))
    load0 = os.getloadavg()[0]  # other jobs on the machine change everything below: say how busy it was
    worker_args = {"map": ["--store-path", str(log_dir / "occvo.sqlite")]} if store else {}
    if working_radius > 0:  # as deployed (deploy/registration_worker.json5): each stream's working map is bounded
        worker_args["registration"] = [
            "--store-path",
            str(log_dir / "registration.sqlite"),
            "--working-radius-m",
            str(working_radius),
        ]
    if after_pose_nice is not None:
        worker_args.setdefault("registration", []).extend(["--after-pose-nice", str(after_pose_nice)])
    if snapshot_max_share is not None:
        worker_args.setdefault("registration", []).extend(["--snapshot-max-share", str(snapshot_max_share)])
    if store_sync is not None:
        worker_args.setdefault("registration", []).extend(["--store-sync", store_sync])
    svc = LocalService(
        common_args=["--policy", policy, "--queue-size", str(queue_size)],
        worker_args=worker_args,
        log_dir=log_dir,
        registration_shards=registration_workers,
    ).start(timeout=120)
    streams = [Stream(f"load{k}", scenes[k][:total], k / n) for k in range(n)]
    subs, pubs, session = [], [], None
    try:
        session = open_session(svc.endpoint)
        for st in streams:
            subs.append(session.declare_subscriber(keys.pose(st.name), st.on_pose))
            pubs.append(
                session.declare_publisher(keys.camera(st.name), congestion_control=zenoh.CongestionControl.BLOCK)
            )

        def on_error(sample):
            try:
                e = decode(sample.payload.to_bytes(), ErrorEvent)
            except CodecError:
                return
            for st in streams:
                if st.name == e.stream:
                    st.errors[e.code] = st.errors.get(e.code, 0) + 1

        subs.append(session.declare_subscriber(keys.errors("*"), on_error))
        deadline = time.monotonic() + 30
        while not all(p.matching_status.matching for p in pubs) and time.monotonic() < deadline:
            time.sleep(0.05)

        # warm-up on a stream of each registration shard (numba compiles on the first frames), outside the measurement
        for w in range(registration_workers):
            name = next(f"warmup{i}" for i in range(1000) if keys.shard_of(f"warmup{i}", registration_workers) == w)
            warm = Stream(name, scenes[0][:3], 0.0)
            subs.append(session.declare_subscriber(keys.pose(name), warm.on_pose))
            wpub = session.declare_publisher(keys.camera(name), congestion_control=zenoh.CongestionControl.BLOCK)
            while not wpub.matching_status.matching and time.monotonic() < deadline:
                time.sleep(0.05)
            for i, occ in enumerate(warm.frames):
                wpub.put(encode(CameraFrame(stream=name, seq=i, stamp=float(i), gt_occupancy=occ, sent_at=time.time())))
                w_deadline = time.monotonic() + 120
                while i not in warm.recv_at and time.monotonic() < w_deadline:
                    time.sleep(0.02)
            pubs.append(wpub)

        procs = {role: psutil.Process(p.pid) for role, p in svc.procs.items()}
        cpu0 = {role: sum(p.cpu_times()[:2]) for role, p in procs.items()}
        io0 = {role: p.io_counters().write_bytes for role, p in procs.items()}
        me0, wall0 = time.process_time(), time.time()
        t0 = time.time() + 1.0
        stop = threading.Event()
        senders = [
            threading.Thread(target=st.send_all, args=(pub, t0, rate, stop), daemon=True)
            for st, pub in zip(streams, pubs)
        ]
        for th in senders:
            th.start()

        samples = []  # (t - t0, registration queue depth total, inference queue depth total, in flight total, reg drops, inf drops)
        next_sample = t0
        t_end = t0 + minutes * 60.0
        while any(th.is_alive() for th in senders) and time.time() < t_end:
            time.sleep(max(0.0, next_sample - time.time()))
            next_sample += sample_s
            reg_q = inf_q = reg_drops = inf_drops = 0
            for r in session.get(keys.stats("*"), timeout=5.0):
                if r.ok is None:
                    continue
                h = decode(r.ok.payload.to_bytes(), WorkerHealth)
                depth = sum(v for s, v in h.queue_depth.items() if s.startswith("load"))
                if h.role == "registration":  # summed over the shards
                    reg_q, reg_drops = reg_q + depth, reg_drops + h.counters.get("drops", 0)
                elif h.role == "inference":
                    inf_q, inf_drops = depth, h.counters.get("drops", 0)
            in_flight = sum(st.last_sent - st.newest_back() for st in streams)
            samples.append((time.time() - t0, reg_q, inf_q, in_flight, reg_drops, inf_drops))
        stop.set()
        for th in senders:
            th.join(60)
        send_end = time.time()
        me1, wall1 = time.process_time(), time.time()
        # drain: every stream's newest frame back (or dropped before it), or time out
        deadline = time.monotonic() + drain_s
        while any(st.newest_back() < st.last_sent for st in streams) and time.monotonic() < deadline:
            time.sleep(0.1)
        drained = all(st.newest_back() >= st.last_sent for st in streams)
        cpu1 = {role: sum(p.cpu_times()[:2]) for role, p in procs.items()}
        io1 = {role: p.io_counters().write_bytes for role, p in procs.items()}
        health, reg_health = {}, []
        for r in session.get(keys.stats("*"), timeout=5.0):
            if r.ok is not None:
                h = decode(r.ok.payload.to_bytes(), WorkerHealth)
                health[h.role] = h
                if h.role == "registration":
                    reg_health.append(h)
    finally:
        if session is not None:
            for x in subs + pubs:
                x.undeclare()
            session.close()
        codes = svc.stop()

    # ---- per bucket of due time (when a camera would have captured the frame), over all streams
    n_buckets = max(1, int(np.ceil(minutes * 60 / bucket_s)))
    buckets = []
    lat_t, lat_v, cap_v, stages, ids = [], [], [], [], []  # due time - t0, sent_at -> pose, due -> pose, timings_ms
    for st in streams:
        for i in range(st.last_sent + 1):
            if i in st.recv_at:
                ids.append((st.name, i))
                lat_t.append(st.due[i] - t0)
                lat_v.append((st.recv_at[i] - st.sent_at[i]) * 1000.0)
                cap_v.append((st.recv_at[i] - st.due[i]) * 1000.0)
                stages.append(st.timings.get(i, {}))
    lat_t, lat_v, cap_v = np.array(lat_t), np.array(lat_v), np.array(cap_v)
    with open(log_dir / "poses.jsonl", "w") as fp:  # every pose, to lay a burst beside the workers' logs (--log-dir)
        for (name, i), t, lat, timing in zip(ids, lat_t, lat_v, stages):
            fp.write(
                json.dumps(
                    {
                        "stream": name,
                        "seq": i,
                        "due_s": round(float(t), 3),
                        "due_unix": float(t + t0),
                        "latency_ms": round(float(lat), 1),
                        "timings_ms": timing,
                    }
                )
                + "\n"
            )
    smp = np.array(samples) if samples else np.zeros((0, 6))
    for b in range(n_buckets):
        lo, hi = b * bucket_s, (b + 1) * bucket_s
        per = []
        lags = []
        for st in streams:
            due = [i for i in range(len(st.frames)) if lo <= st.due[i] - t0 < hi]
            sent = [i for i in due if st.sent_at[i] == st.sent_at[i]]
            lags += [st.lag[i] for i in sent]
            arrived = sum(1 for t in st.recv_at.values() if lo <= t - t0 < hi)
            per.append(
                {
                    "due": len(due),
                    "sent": len(sent),
                    "received": sum(1 for i in sent if i in st.recv_at),
                    "arrived": arrived,
                }
            )
        in_b = (lat_t >= lo) & (lat_t < hi)
        slow = np.flatnonzero(in_b & (lat_v >= (_pct(lat_v[in_b], 99) or np.inf)))
        # waiting (hops between processes, time in a worker's queue) vs working: a backlog shows in the first
        wait = [sum(v for k, v in stages[j].items() if k.endswith(("_hop", "_queue"))) for j in np.flatnonzero(in_b)]
        sm = smp[(smp[:, 0] >= lo) & (smp[:, 0] < hi)] if len(smp) else smp
        buckets.append(
            {
                "t0_s": lo,
                "due": sum(p["due"] for p in per),
                "sent": sum(p["sent"] for p in per),
                "received": sum(p["received"] for p in per),
                "poses_per_s": sum(p["arrived"] for p in per) / bucket_s,
                "per_stream": {st.name: f"{p['sent']}/{p['received']}" for st, p in zip(streams, per)},
                "latency_p50_ms": _pct(lat_v[in_b], 50),
                "latency_p99_ms": _pct(lat_v[in_b], 99),
                "capture_latency_p50_ms": _pct(cap_v[in_b], 50),
                "capture_latency_p99_ms": _pct(cap_v[in_b], 99),
                "send_lag_max_ms": float(max(lags) * 1000.0) if lags else None,
                "reg_queue_mean": float(sm[:, 1].mean()) if len(sm) else None,
                "reg_queue_max": int(sm[:, 1].max()) if len(sm) else None,
                "in_flight_mean": float(sm[:, 3].mean()) if len(sm) else None,
                "in_flight_max": int(sm[:, 3].max()) if len(sm) else None,
                "slowest_1pct_stage_ms": _stage_medians([stages[j] for j in slow]),
                "wait_p50_ms": _pct(wait, 50),
                "wait_p99_ms": _pct(wait, 99),
                # which poses they were: a burst on one stream (its loop closure) reads differently from one on all
                "slowest_poses": [
                    {
                        "stream": ids[j][0],
                        "seq": ids[j][1],
                        "latency_ms": round(float(lat_v[j]), 1),
                        **{
                            k: round(float(stages[j][k]), 1)
                            for k in ("registration_queue", "registration", "store_commit")
                            if k in stages[j]
                        },
                    }
                    for j in sorted(slow, key=lambda j: -lat_v[j])[:8]
                ],
            }
        )
    sent = sum(st.last_sent + 1 for st in streams)
    received = sum(len([s for s in st.recv_at if s <= st.last_sent]) for st in streams)
    due_total = sum(len(st.frames) for st in streams)
    first, last = buckets[0]["latency_p99_ms"], buckets[-1]["latency_p99_ms"]
    wfirst, wlast = buckets[0]["wait_p99_ms"], buckets[-1]["wait_p99_ms"]
    cfirst, clast = buckets[0]["capture_latency_p99_ms"], buckets[-1]["capture_latency_p99_ms"]
    # sharded: the stage figures below are the busiest shard's
    reg = max(reg_health, key=lambda h: h.counters.get("frames_out", 0), default=None)
    mp = health.get("map")
    build = np.concatenate([st.build_ms for st in streams])
    put = np.concatenate([st.put_ms for st in streams])
    lag = np.concatenate([st.lag for st in streams])
    offered = n * rate
    last_rate = buckets[-1]["poses_per_s"]
    out = {
        "streams": n,
        "rate_hz": rate,
        "minutes": minutes,
        "policy": policy,
        "queue_size": queue_size,
        "store": store,
        "registration_workers": registration_workers,
        "after_pose_nice": after_pose_nice,
        "snapshot_max_share": snapshot_max_share,
        "store_sync": store_sync,
        "working_radius_m": working_radius or None,
        "offered_frames_per_s": offered,
        "due": due_total,
        "sent": sent,
        "received": received,
        "drained": drained,
        "drops": {
            "registration": int(smp[-1, 4]) if len(smp) else 0,
            "inference": int(smp[-1, 5]) if len(smp) else 0,
            "registration_final": sum(h.counters.get("drops", 0) for h in reg_health) if reg_health else None,
        },
        "errors": {st.name: st.errors for st in streams if st.errors},
        "p99_ratio_last_first": (last / first) if first and last else None,
        "capture_p99_ratio_last_first": (clast / cfirst) if cfirst and clast else None,
        "wait_p99_ratio_last_first": (wlast / wfirst) if wfirst and wlast else None,
        "slope_capture_latency_ms_per_min": _slope(lat_t, cap_v),
        "slope_reg_queue_per_min": _slope(smp[:, 0], smp[:, 1]) if len(smp) else None,
        "slope_in_flight_per_min": _slope(smp[:, 0], smp[:, 3]) if len(smp) else None,
        "slope_latency_ms_per_min": _slope(lat_t, lat_v),
        "last_bucket_poses_per_s": last_rate,
        "registration_ms_p50": reg.stages["registration"].p50_ms if reg and "registration" in reg.stages else None,
        "registration_stage_mean_ms": reg.stages["stage_total"].mean_ms
        if reg and "stage_total" in reg.stages
        else None,
        "map_update_ms_p50": reg.stages["map_update"].p50_ms if reg and "map_update" in reg.stages else None,
        "worker_cpu_pct": {role: 100.0 * (cpu1[role] - cpu0[role]) / (time.time() - wall0) for role in cpu0},
        "worker_disk_write_mb_per_s": {role: (io1[role] - io0[role]) / 2**20 / (time.time() - wall0) for role in io0},
        "registration_counters": {
            k: sum(h.counters.get(k, 0) for h in reg_health)
            for k in ("loop_closures", "after_pose_boosted", "tiles_evicted", "tiles_restored")
        },
        "client_and_router_cpu_pct": 100.0 * (me1 - me0) / (wall1 - wall0),
        "client_build_ms_p50": _pct(build, 50),
        "client_build_ms_p99": _pct(build, 99),
        "client_put_ms_p50": _pct(put, 50),
        "client_put_ms_p99": _pct(put, 99),
        "send_lag_ms_p50": (_pct(lag, 50) or 0) * 1000.0,
        "send_lag_ms_max": float(np.nanmax(lag) * 1000.0) if len(lag) else None,
        "map_apply_ms_p50": mp.stages["apply_update"].p50_ms if mp and "apply_update" in mp.stages else None,
        "map_apply_ms_p99": mp.stages["apply_update"].p99_ms if mp and "apply_update" in mp.stages else None,
        "loadavg_1min_start_end": [load0, os.getloadavg()[0]],
        "worker_exit_codes": codes,
        "buckets": buckets,
        "send_seconds": send_end - t0,
    }
    # keeps up: every frame sent on time and answered, poses come back at the offered rate, frames in flight grow by
    # less than one per stream per minute, and the median latency does not double (p99 of a short bucket is its max)
    c50 = [b["capture_latency_p50_ms"] for b in buckets]
    out["capture_p50_ratio_last_first"] = c50[-1] / c50[0] if c50[0] and c50[-1] else None
    out["keeps_up"] = bool(
        sent == due_total
        and received >= 0.99 * sent
        and drained
        and last_rate >= 0.95 * offered
        and (out["slope_in_flight_per_min"] or 0) <= n
        and (out["capture_p50_ratio_last_first"] or 99) <= 2.0
    )
    return out


def print_run(r: dict, bucket_s: float) -> None:
    print(
        f"\n== {r['streams']} streams x {r['rate_hz']:g} Hz, {r['minutes']:g} min, policy {r['policy']}, "
        f"queue {r['queue_size']}, map store {'sqlite' if r['store'] else 'memory'}, registration "
        + (f"store + eviction at {r['working_radius_m']:g} m" if r["working_radius_m"] else "in memory, no eviction")
        + (f", {r['registration_workers']} registration workers (shards)" if r["registration_workers"] > 1 else "")
        + (f", a neighbour busy {r['neighbour_load']:g} of every core" if r.get("neighbour_load") else "")
    )
    unit = "min" if bucket_s == 60 else f"{bucket_s:g}s"
    print(
        f"{unit:>5} {'due':>5} {'sent':>5} {'recv':>5} {'poses/s':>7} {'lat p50':>7} {'lat p99':>7} {'cap p50':>7} {'cap p99':>7} "
        f"{'lag max':>7} {'regQ':>5} {'regQmax':>7} {'inflight':>8}  per stream sent/recv"
    )
    fmt = lambda v, f="{:.0f}": "-" if v is None else f.format(v)  # noqa: E731
    for b, x in enumerate(r["buckets"]):
        print(
            f"{b + 1:>5} {x['due']:>5} {x['sent']:>5} {x['received']:>5} {x['poses_per_s']:>7.2f} {fmt(x['latency_p50_ms']):>7} "
            f"{fmt(x['latency_p99_ms']):>7} {fmt(x['capture_latency_p50_ms']):>7} {fmt(x['capture_latency_p99_ms']):>7} "
            f"{fmt(x['send_lag_max_ms']):>7} {fmt(x['reg_queue_mean'], '{:.1f}'):>5} {fmt(x['reg_queue_max']):>7} "
            f"{fmt(x['in_flight_max']):>8}  {' '.join(x['per_stream'].values())}"
        )
    print(
        "waiting (hops + worker queues) p50/p99, and the slowest 1%: median ms of the stages that took most (timings_ms):"
    )
    for b, x in enumerate(r["buckets"]):
        top = list(x.get("slowest_1pct_stage_ms", {}).items())[:6]
        print(
            f"{b + 1:>5}  wait {fmt(x.get('wait_p50_ms'))}/{fmt(x.get('wait_p99_ms'))}  slowest: "
            + ", ".join(f"{k} {v:.0f}" for k, v in top)
        )
    print(
        "(ms; lat = client send -> pose; cap = due time -> pose, what a live camera sees; lag = send - due; regQ = registration "
        "queue depth summed over streams, sampled)"
    )
    print(
        f"due {r['due']} sent {r['sent']} received {r['received']} (offered {r['offered_frames_per_s']:g} frames/s, last bucket "
        f"{r['last_bucket_poses_per_s']:.2f} poses/s), drops reg/inf {r['drops']['registration_final']}/{r['drops']['inference']}, "
        f"drained {r['drained']}"
    )
    print(
        f"backlog: p99 last/first: wait {fmt(r.get('wait_p99_ratio_last_first'), '{:.2f}')}, latency {fmt(r['p99_ratio_last_first'], '{:.2f}')}, capture latency "
        f"{fmt(r['capture_p99_ratio_last_first'], '{:.2f}')} (p50 {fmt(r['capture_p50_ratio_last_first'], '{:.2f}')}); slopes per minute: capture latency "
        f"{fmt(r['slope_capture_latency_ms_per_min'], '{:+.0f}')} ms, registration queue "
        f"{fmt(r['slope_reg_queue_per_min'], '{:+.2f}')}, frames in flight {fmt(r['slope_in_flight_per_min'], '{:+.2f}')}, "
        f"latency {fmt(r['slope_latency_ms_per_min'], '{:+.0f}')} ms  ->  keeps up: {r['keeps_up']}"
    )
    busiest = " (busiest shard)" if r["registration_workers"] > 1 else ""
    print(
        f"registration{busiest} p50 {fmt(r['registration_ms_p50'], '{:.1f}')} ms, stage mean {fmt(r['registration_stage_mean_ms'], '{:.1f}')} ms, "
        f"map tiling p50 {fmt(r['map_update_ms_p50'], '{:.1f}')} ms; map service apply p50/p99 {fmt(r['map_apply_ms_p50'], '{:.1f}')}/"
        f"{fmt(r['map_apply_ms_p99'], '{:.1f}')} ms; load avg start/end {r['loadavg_1min_start_end'][0]:.1f}/"
        f"{r['loadavg_1min_start_end'][1]:.1f}; CPU % "
        f"{json.dumps({k: round(v) for k, v in r['worker_cpu_pct'].items()})}, client+router {r['client_and_router_cpu_pct']:.0f}%"
    )
    print(
        f"client per frame: build+encode p50 {fmt(r['client_build_ms_p50'], '{:.2f}')} ms p99 {fmt(r['client_build_ms_p99'], '{:.2f}')} ms, "
        f"put p50 {fmt(r['client_put_ms_p50'], '{:.2f}')} ms p99 {fmt(r['client_put_ms_p99'], '{:.2f}')} ms, send lag p50 "
        f"{r['send_lag_ms_p50']:.1f} ms max {fmt(r['send_lag_ms_max'], '{:.0f}')} ms; errors {r['errors'] or 'none'}; "
        f"exit codes {r['worker_exit_codes']}"
    )
    print(
        f"registration counters (all shards): {json.dumps(r['registration_counters'])}; disk writes MB/s "
        f"{json.dumps({k: round(v, 1) for k, v in r['worker_disk_write_mb_per_s'].items()})}"
    )


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
