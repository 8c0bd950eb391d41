"""Hostile-client step store_flood: one client opening fresh streams for minutes against the plain default
(benchmarks/hostile_clients.py)."""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import zenoh
from _hostile_common import BLOCK, counters, emit, goal
from _hostile_deploy import deploy
from _hostile_identity import borrowed_ids

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_services.client import camera_frame_of
from occvo_services.runtime import WorkerConfig
from occvo_services.store.factory import open_store

DEFAULTS = "services/defaults"  # what `occvo serve` runs


def _files_bytes(folder: Path) -> dict[str, int]:
    return {p.name: p.stat().st_size for p in sorted(folder.iterdir()) if p.is_file()}


def _flood(session, login, ids, frame, seconds: float, period_s: float) -> int:
    """A seq-0 frame on a fresh stream id every period_s for `seconds`, as one client (one login), each stream's
    frame under the next of `ids` (rotating ids); how many streams."""
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        stream = deploy().wire(f"sflood{n}", login)
        data = encode(camera_frame_of(frame, stream, 0, exact=False))  # ~11 ms: well within a period
        zid = ids[n % len(ids)]
        session.put(keys.camera(stream), data, congestion_control=BLOCK, source_info=zenoh.SourceInfo(zid, n + 1))
        n += 1
        time.sleep(max(0.0, t0 + n * period_s - time.perf_counter()))
    return n


def _stored(url: str, prefix: str) -> tuple[list[str], dict]:
    """The streams stored under `prefix` and {client: (streams, bytes)} of their clients, as the store records."""
    s = open_store(url)
    try:
        stored = [x for x in s.streams() if x.startswith(prefix)]
        return stored, {c: s.usage(c) for c in {s.stream_usage(x)[0] for x in stored}}
    finally:
        s.close()


def store_flood(args, frames) -> None:
    """One session putting a seq-0 frame on a fresh stream id every --store-flood-period-s for --store-flood-s
    (default 180 s) against `occvo serve`'s worker configs with a SQLite store shared by the
    registration worker and the map service. Once every stream is idle (idle_stream_s) and snapshotted: the store's
    growth (its files once the workers stopped, their WALs checkpointed into them) against the client's quota, the
    workers' log bytes against 10 MB, streams stored and refused."""
    reg_config = f"{DEFAULTS}/registration_worker.json5"
    config = WorkerConfig.load(reg_config)
    quota_mb, idle_s = config.max_store_mb_per_client, config.idle_stream_s
    folder, logs = Path(tempfile.mkdtemp()), Path(tempfile.mkdtemp())
    store = ["--store-path", str(folder / "occvo.sqlite")]
    svc = (
        deploy()
        .service(
            log_dir=logs,
            worker_args={
                "registration": ["--config", reg_config, *store],
                "inference": ["--config", f"{DEFAULTS}/inference_worker.json5"],
                "map": ["--config", f"{DEFAULTS}/map_service.json5", *store],
            },
        )
        .start()
    )
    try:
        files0, logs0 = _files_bytes(folder), sum(_files_bytes(logs).values())
        session, login = deploy().attacker(svc.endpoint, "own")
        ids = borrowed_ids(svc.endpoint, 64)
        opened = _flood(session, login, ids, frames[0], args.store_flood_s, args.store_flood_period_s)
        time.sleep(idle_s + 30.0)  # every flood stream idle: retired, snapshotted, measured
        names = ("frames_refused_quota", "streams_refused", "streams_refused_memory", "snapshots", "streams_retired")
        reg = counters(session, svc, "registration", names)
        session.close()
    finally:
        svc.stop()
    files1, logs1 = _files_bytes(folder), sum(_files_bytes(logs).values())
    growth = sum(files1.values()) - sum(files0.values())
    stored, usage = _stored(store[1], deploy().wire("sflood", login))
    shutil.rmtree(folder, ignore_errors=True)  # a GiB or two a pass
    shutil.rmtree(logs, ignore_errors=True)
    emit(
        "store_flood",
        mode=deploy().name,
        rotating_ids=len(ids),
        flood_s=args.store_flood_s,
        streams_opened=opened,
        streams_stored=len(stored),
        client_usage_mb={c[:8]: round(b / 2**20, 1) for c, (_, b) in usage.items()},
        store_growth_mb=round(growth / 2**20, 1),
        store_files_mb={k: round(v / 2**20, 1) for k, v in files1.items()},
        log_mb=round((logs1 - logs0) / 2**20, 2),
        max_store_mb_per_client=quota_mb,
        registration=reg,
    )
    goal(
        "one client's stream flood under 64 rotating ids adds at most its quota to the store",
        growth <= quota_mb << 20,
        growth_mb=round(growth / 2**20, 1),
        quota_mb=quota_mb,
    )
    goal("and the log at most 10 MB", logs1 - logs0 <= 10 << 20, log_mb=round((logs1 - logs0) / 2**20, 2))
