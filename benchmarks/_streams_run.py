"""streams_load.py's run: the service up (LocalService), every stream sending at its rate from its own thread, the
workers' queues sampled; what came back is summarised by _streams_report."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import zenoh
from _streams_report import summarise
from _streams_scenes import Stream

from occvo_schemas import keys
from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.models import CameraFrame, ErrorEvent, WorkerHealth
from occvo_services.client import OccVOClient
from occvo_services.local import LocalService
from occvo_services.sessions import open_session


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
    placement: str = "shards",
) -> dict:
    import psutil

    total = int(round(minutes * 60 * rate))
    load0 = os.getloadavg()[0]  # other jobs on the machine change everything below: say how busy it was
    worker_args = {"map": ["--store-path", str(log_dir / "occvo.sqlite")]} if store else {}
    if working_radius > 0:  # as deployed (deploy/registration_worker.json5): each stream's working map is bounded
        # the streams here are many cars under one login: a car's store quota (a client's) would count them all
        (log_dir / "registration.json5").write_text("{max_store_mb_per_client: null}\n")
        worker_args["registration"] = [
            "--config",
            str(log_dir / "registration.json5"),
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
        placement=placement,
    ).start(timeout=120)
    streams = [Stream(f"load{k}", scenes[k][:total], k / n) for k in range(n)]
    subs, pubs, clients, session = [], [], [], None
    try:
        session = open_session(svc.endpoint)
        for st in streams:  # each a car's client: it sends again what a full queue turned away (lossless)
            subs.append(session.declare_subscriber(keys.pose(st.name), st.on_pose))
            clients.append(OccVOClient(svc.endpoint, st.name, timeout=60.0, session=session))

        def on_error(sample):
            try:
                e = decode(sample.payload.to_bytes(), ErrorEvent)
            except CodecError:
                return
            for st in streams:
                if st.name == e.stream and e.code != "stream_full":  # flow control: the client counts and resends
                    st.errors[e.code] = st.errors.get(e.code, 0) + 1

        subs.append(session.declare_subscriber(keys.errors("*"), on_error))
        deadline = time.monotonic() + 30

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
            threading.Thread(target=st.send_all, args=(client, t0, rate, stop), daemon=True)
            for st, client in zip(streams, clients)
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
        for st, client in zip(streams, clients):
            st.turned_away, st.resends = client.turned_away, client.resends
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
        for client in clients:
            client.close()
        if session is not None:
            for x in subs + pubs:
                x.undeclare()
            session.close()
        codes = svc.stop()
    return summarise(
        dict(
            n=n,
            rate=rate,
            minutes=minutes,
            policy=policy,
            queue_size=queue_size,
            store=store,
            bucket_s=bucket_s,
            log_dir=log_dir,
            working_radius=working_radius,
            registration_workers=registration_workers,
            after_pose_nice=after_pose_nice,
            snapshot_max_share=snapshot_max_share,
            store_sync=store_sync,
            placement=placement,
            load0=load0,
            streams=streams,
            samples=samples,
            t0=t0,
            send_end=send_end,
            drained=drained,
            codes=codes,
            health=health,
            reg_health=reg_health,
            cpu0=cpu0,
            cpu1=cpu1,
            io0=io0,
            io1=io1,
            me0=me0,
            me1=me1,
            wall0=wall0,
            wall1=wall1,
        )
    )
