"""What the hostile-client steps share (benchmarks/hostile_clients.py): workers' status, counters, a grabber, a replay, the JSON lines."""

from __future__ import annotations

import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from _common import SAMPLE

from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import ErrorEvent, WorkerHealth
from occvo_services.client import OccVOClient, camera_frame_of
from occvo_services.commands.replay import replay
from occvo_services.sessions import open_login, open_session

DATA = SAMPLE / "occupancy" / "scene-0101"
BLOCK = zenoh.CongestionControl.BLOCK


def proc_status(pid: int) -> dict:
    out = {}
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        k, _, v = line.partition(":")
        if k in ("VmRSS", "Threads"):
            out[k] = int(v.split()[0])
    return {"rss_mb": round(out["VmRSS"] / 1024, 1), "threads": out["Threads"]}


def cpu_s(pid: int) -> float:
    f = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / os.sysconf("SC_CLK_TCK")


def workers(svc) -> dict:
    return {r: proc_status(p.pid) for r, p in svc.procs.items()}


def worker_args(reg_config: str, reg_cap: list[str], store: list[str]) -> dict:
    """LocalService's worker arguments: the deploy configs, the store (--store-path), the registration cap."""
    return {
        "registration": ["--config", reg_config, *store, *reg_cap],
        "inference": ["--config", "deploy/inference_worker.json5"],
        "map": ["--config", "deploy/map_service.json5", *store],
    }


def counters(session, svc, role: str, names: tuple[str, ...]) -> dict:
    """Some of a worker's counters, from its stats queryable (LocalService names it <role>-<our pid>); behind access
    control through the router's own session (a client login may not read stats)."""
    asker = svc.router if svc.router_config else session
    for r in asker.get(keys.stats(f"{role}-{os.getpid()}"), timeout=10.0):
        if r.ok is not None:
            got = decode(r.ok.payload.to_bytes(), WorkerHealth).counters
            return {n: got.get(n, 0) for n in names}
    return {}


def wildcard_gets(endpoint: str, threads: int, stop, counts, base=None) -> None:
    """A client (its zenoh config `base`) looping `occvo/**` gets on `threads` threads until `stop`; counts[0] ok
    replies, counts[1] busy, counts[2] gets done."""
    session = open_session(endpoint, base, pick_up=False)

    def loop():
        while not stop.is_set():
            for r in session.get("occvo/**", timeout=10.0):
                busy = r.err is not None and decode(r.err.payload.to_bytes(), ErrorEvent).code == "busy"
                with counts.get_lock():
                    counts[int(busy)] += 1
            with counts.get_lock():
                counts[2] += 1

    ts = [threading.Thread(target=loop) for _ in range(threads)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    session.close()


def emit(step: str, **fields) -> None:
    print(json.dumps({"step": step, **fields}), flush=True)


GOALS: list[bool] = []  # every goal line so far: the script exits 1 if one is not met


def goal(text: str, met: bool, **figure) -> None:
    """A goal line; in the anonymous mode it is advisory (said, not counted): its guards rest on self-declared ids."""
    from _hostile_deploy import DEPLOY

    advisory = bool(DEPLOY) and DEPLOY[-1].anonymous
    if not advisory:
        GOALS.append(bool(met))
    mode = DEPLOY[-1].name if DEPLOY else None
    print(json.dumps({"goal": text, "met": bool(met), "mode": mode, "advisory": advisory, **figure}), flush=True)


def grab(endpoint: str, streams: list[str], frame, stop: threading.Event, period_s: float = 2.0, base=None) -> None:
    """A slot grabber: one session (its zenoh config `base`) putting a seq-0 frame on each of `streams` every
    period_s until stop."""
    session = open_session(endpoint, base)
    payloads = [(keys.camera(s), encode(camera_frame_of(frame, s, 0))) for s in streams]
    sn = 0
    while not stop.is_set():
        t0 = time.monotonic()
        for key, payload in payloads:
            sn += 1
            session.put(key, payload, congestion_control=BLOCK, source_info=zenoh.SourceInfo(session.id, sn))
        stop.wait(max(0.0, period_s - (time.monotonic() - t0)))
    session.close()


def run_replay(endpoint: str, stream: str, frames, base=None) -> tuple[float, np.ndarray]:
    """The replay of `frames` on `stream` (its session's zenoh config `base`): its time and poses."""
    session, login = open_login(endpoint, base)
    with session, OccVOClient(endpoint, stream, timeout=300, session=session, login=login) as c:
        t0 = time.perf_counter()
        out = replay(c, frames, window=4, timeout=600)
        took = time.perf_counter() - t0
        poses = np.array([c.poses[i].matrix() for i in sorted(c.poses)]) if c.poses else np.zeros((0, 4, 4))
        codes = sorted({(e.worker.split("-")[0], e.code, e.message[:120]) for e in c.errors})
    assert out["poses"] == len(frames), (out["poses"], out["errors"], codes)
    return took, poses
