"""Hostile-client steps on a PostgreSQL store of their own (services/store/pg_local.py; benchmarks/hostile_clients.py):
db_outage (the database stopped mid-drive), members_acl (placement members under the shipped ACL, an owner killed),
lease_flood (one-byte puts on new keys against placement members), share_flood (valid frames on new streams beyond
a client's share)."""

from __future__ import annotations

import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import zenoh
from _hostile_acl import acl_logins
from _hostile_common import BLOCK, counters, emit, goal
from _hostile_deploy import deploy

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_schemas.models import OccupancyFrameMsg
from occvo_services.camera_frames import camera_frame_of
from occvo_services.client import OccVOClient, ServiceError
from occvo_services.commands.replay import replay
from occvo_services.sessions import ZENOH_CONFIG_ENV, open_login
from occvo_services.store.factory import open_store
from occvo_services.store.pg_local import PgCluster

DEFAULTS = "services/defaults"  # what `occvo serve` runs


def _serve_args(url: str) -> dict:
    store = ["--store-url", url]
    return {
        "registration": ["--config", f"{DEFAULTS}/registration_worker.json5", *store],
        "inference": ["--config", f"{DEFAULTS}/inference_worker.json5"],
        "map": ["--config", f"{DEFAULTS}/map_service.json5", *store],
    }


def _replays(endpoint: str, streams: list[str], frames, at: int, event, base=None, timeout: float = 900) -> dict:
    """The replays of `frames` on `streams` side by side (window 4); event() runs once each has pose `at`. Per
    stream: its poses, seconds, resends and error codes."""
    session, login = open_login(endpoint, base)
    clients = {s: OccVOClient(endpoint, s, timeout=600, session=session, login=login) for s in streams}
    out: dict = {}

    def run(stream: str) -> None:
        c = clients[stream]
        c.reset()
        t0 = time.perf_counter()
        try:
            got = replay(c, frames, window=4, timeout=timeout)
        except ServiceError:  # stalled: no pose for `timeout` s
            got = {"resends": c.resends}
        poses = np.array([c.poses[i].matrix() for i in sorted(c.poses)]) if c.poses else np.zeros((0, 4, 4))
        codes = sorted({e.code for e in c.errors})
        out[stream] = {"poses": poses, "s": time.perf_counter() - t0, "resends": got["resends"], "codes": codes}

    threads = [threading.Thread(target=run, args=(s,)) for s in streams]
    for t in threads:
        t.start()
    deadline = time.monotonic() + min(600, timeout)
    while any(at not in c.poses for c in clients.values()) and time.monotonic() < deadline:
        time.sleep(0.05)
    event()
    for t in threads:
        t.join()
    for c in clients.values():
        c.close()
    session.close()
    return out


def _stored_equal(url: str, streams: list[str], alone: np.ndarray) -> bool:
    store = open_store(url)
    try:
        return all(np.array_equal(np.array([p.pose for p in store.poses(s)]), alone) for s in streams)
    finally:
        store.close()


def db_outage(outage_s: float, frames, alone: np.ndarray) -> None:
    """`occvo serve`'s worker configs on PostgreSQL, two replays; the database stopped for `outage_s` once both have
    pose 10: each replay's poses and the stored ones vs alone, the codes its client got, its resends and time."""
    cluster = PgCluster()
    url = cluster.new_database()
    svc = deploy().service(quiet=True, worker_args=_serve_args(url)).start()
    down: list[float] = []

    def outage() -> None:
        t0 = time.monotonic()
        cluster.stop()
        time.sleep(outage_s)
        cluster.start()
        down.append(time.monotonic() - t0)

    try:
        streams = [deploy().victim_stream(f"outage{i}") for i in range(2)]
        got = _replays(svc.endpoint, streams, frames, 10, outage)
        stored = _stored_equal(url, streams, alone)
    finally:
        svc.stop()
        cluster.close()
    equal = all(len(g["poses"]) == len(frames) and np.array_equal(g["poses"], alone) for g in got.values())
    figures = {s: {k: (round(v, 1) if k == "s" else v) for k, v in g.items() if k != "poses"} for s, g in got.items()}
    emit("db_outage", outage_s=round(down[0], 1), poses={s: len(g["poses"]) for s, g in got.items()}, **figures)
    goal(
        f"the database stopped {outage_s:.0f} s mid-drive: every stream all its poses, equal to alone's, stored",
        equal and stored,
        stored_equal=stored,
    )


def members_acl(frames, alone: np.ndarray, shipped: bool) -> None:
    """Two registration workers in placement members behind the shipped ACL (`shipped`: deploy/acl, each the
    `registration` login, four replays as the `camera` login) or the default deployment's (the workers' logins, the
    replays the user's); the owner of the first stream killed (-9) at its pose 10: every pose vs alone, owners."""
    cluster, folder = PgCluster(), Path(tempfile.mkdtemp())
    url = cluster.new_database()
    kw = {"registration_shards": 2, "placement": "members", "worker_args": _serve_args(url)}
    if shipped:
        router, sessions = acl_logins(folder, ["camera"])
        env = {role: {ZENOH_CONFIG_ENV: str(sessions[role])} for role in ("inference", "registration", "map")}
        kw.update(router_config=str(router), worker_env=env)
        base, streams = sessions["camera"], [f"camera.m{i}" for i in range(4)]
    else:
        base, streams = None, [deploy().victim_stream(f"m{i}") for i in range(4)]
    svc = deploy().service(quiet=True, **kw).start()
    killed = []

    def kill_owner() -> None:
        store = open_store(url)
        owners = {store.owner_of(s) for s in streams}
        victim = store.owner_of(streams[0])
        store.close()
        name = victim.rsplit("-", 1)[0]
        svc.procs[name].kill()
        killed.append((victim, sorted(owners)))

    try:
        got = _replays(svc.endpoint, streams, frames, 10, kill_owner, base)
        stored = _stored_equal(url, streams, alone)
    finally:
        svc.stop()
        cluster.close()
    victim, owners = killed[0]
    equal = all(len(g["poses"]) == len(frames) and np.array_equal(g["poses"], alone) for g in got.values())
    acl = "the shipped ACL" if shipped else "the default's logins"
    emit("members_acl", acl=acl, owners_before=owners, killed=victim, **{s: g["codes"] for s, g in got.items()})
    goal(f"members under {acl}: both took streams before the kill", len(owners) == 2, owners=owners)
    goal(
        f"members under {acl}, an owner killed (-9): every stream all its poses, equal to alone's, stored",
        equal and stored,
    )


def lease_flood(args, frames, alone_s: float, alone: np.ndarray) -> None:
    """Placement members (one worker) on PostgreSQL: one session puts --lease-flood one-byte payloads on new keys
    while a replay runs: its poses vs alone and its time vs solo, the lease rows left once the flood is over."""
    cluster = PgCluster()
    url = cluster.new_database()
    svc = deploy().service(quiet=True, placement="members", worker_args=_serve_args(url)).start()
    stop, sent = threading.Event(), [0]

    def flood() -> None:  # on occupancy keys (as the inference worker would) and on its own camera keys
        session, login = deploy().attacker(svc.endpoint, "own")
        while not stop.is_set() and sent[0] < args.lease_flood:
            kind = ("occupancy", "camera")[sent[0] % 2]
            session.put(f"occvo/{deploy().wire(f'lease{sent[0]}', login)}/{kind}", b"x", congestion_control=BLOCK)
            sent[0] += 1
        session.close()

    try:
        flooder = threading.Thread(target=flood)
        legit = deploy().victim_stream("leaselegit")
        got = _replays(svc.endpoint, [legit], frames, 0, flooder.start)[legit]
        stop.set()
        flooder.join()
        time.sleep(5.0)  # one lease renewal pass at least (lease_s / 3)
        store = open_store(url)
        rows = sorted(lease.stream for lease in store.leases())
        store.close()
    finally:
        svc.stop()
        cluster.close()
    equal = len(got["poses"]) == len(frames) and np.array_equal(got["poses"], alone)
    emit("lease_flood", mode=deploy().name, puts=sent[0], replay_s=round(got["s"], 1), alone_s=round(alone_s, 1),
         lease_rows=rows[:8], lease_row_count=len(rows))  # fmt: skip
    goal("lease flood: the replay gets every pose, equal to alone's", equal)
    goal("lease flood: the replay within 3x its solo time", got["s"] <= 3 * alone_s, ratio=round(got["s"] / alone_s, 2))
    goal("lease flood: no lease row but the replay's", rows == [legit], lease_rows=len(rows))


def share_flood(args, frames, alone_s: float, alone: np.ndarray) -> None:
    """Placement members (one worker) on PostgreSQL: one client puts a valid frame on each of --share-flood new
    stream ids while a replay runs (logins: its own login's camera frames, through the inference worker; anonymous:
    occupancy frames put straight to the registration worker under one session): the replay's poses vs alone and its
    time vs solo, the most lease rows during the flood, the worker's placements and refusals before placement."""
    cluster = PgCluster()
    url = cluster.new_database()
    svc = deploy().service(quiet=True, placement="members", worker_args=_serve_args(url)).start()
    stop, sent, peak = threading.Event(), [0], [0]

    def flood() -> None:
        session, login = deploy().attacker(svc.endpoint, "own")
        while not stop.is_set() and sent[0] < args.share_flood:
            stream = deploy().wire(f"share{sent[0]}", login)
            cam = camera_frame_of(frames[0], stream, 0)
            if deploy().anonymous:  # one session's zid: one client, its frames straight to registration
                occ = OccupancyFrameMsg(stream=stream, seq=0, stamp=cam.stamp, source="replay",
                                        occupancy=cam.gt_occupancy, timings_ms={})  # fmt: skip
                key, payload = keys.occupancy(stream), encode(occ)
            else:
                key, payload = keys.camera(stream), encode(cam)
            session.put(key, payload, congestion_control=BLOCK, source_info=zenoh.SourceInfo(session.id, sent[0] + 1))
            sent[0] += 1
        session.close()

    def watch() -> None:
        store = open_store(url)
        while not stop.wait(0.2):
            peak[0] = max(peak[0], len(store.leases()))
        store.close()

    try:
        threads = [threading.Thread(target=flood), threading.Thread(target=watch)]
        legit = deploy().victim_stream("sharelegit")
        got = _replays(svc.endpoint, [legit], frames, 0, lambda: [t.start() for t in threads])[legit]
        while threads[0].is_alive() and sent[0] < args.share_flood:
            time.sleep(0.2)
        time.sleep(2.0)  # the last frames judged
        stop.set()
        for t in threads:
            t.join()
        probe, _ = deploy().attacker(svc.endpoint, "own")
        placed = counters(probe, svc, "registration", ("frames_placed", "frames_refused_before_placement"))
        probe.close()
    finally:
        svc.stop()
        cluster.close()
    share = 16  # max_streams_per_client of services/defaults/registration_worker.json5, one member
    equal = len(got["poses"]) == len(frames) and np.array_equal(got["poses"], alone)
    emit("share_flood", mode=deploy().name, streams=sent[0], replay_s=round(got["s"], 1), alone_s=round(alone_s, 1),
         peak_lease_rows=peak[0], **placed)  # fmt: skip
    goal("share flood: the replay gets every pose, equal to alone's", equal)
    goal("share flood: the replay within 3x its solo time", got["s"] <= 3 * alone_s, ratio=round(got["s"] / alone_s, 2))
    goal("share flood: lease rows at most the client's share and the replay's", peak[0] <= share + 1, peak=peak[0])


def fake_tokens(frames, alone: np.ndarray, n: int = 8) -> None:
    """Placement members (one worker) on PostgreSQL: the attacker (its own login) declares n registration workers'
    liveliness tokens, then the victim replays two streams: their poses vs alone, their time vs the same two replays
    before the tokens, leases held by fake workers."""
    cluster = PgCluster()
    url = cluster.new_database()
    svc = deploy().service(quiet=True, placement="members", worker_args=_serve_args(url)).start()
    session, _ = deploy().attacker(svc.endpoint, "own")
    tokens = []
    try:  # the two replays side by side on this service first: the time to compare with
        solo = _replays(svc.endpoint, [deploy().victim_stream(f"solo{i}") for i in range(2)], frames, 0, lambda: None)
        alone_s = max(g["s"] for g in solo.values())
        for i in range(n):
            for key in (keys.registration_shard(0, 0, f"fake{i}"), keys.alive("registration", f"fake{i}")):
                try:
                    tokens.append(session.liveliness().declare_token(key))
                except Exception:  # noqa: BLE001 - refused locally: nothing declared
                    pass
        time.sleep(2.0)
        streams = [deploy().victim_stream(f"tok{i}") for i in range(2)]
        got = _replays(svc.endpoint, streams, frames, 0, lambda: None, timeout=120)  # a stalled one: 120 s
        store = open_store(url)
        owners = sorted({lease.owner or "(released)" for lease in store.leases() if "solo" not in lease.stream})
        store.close()
    finally:
        for t in tokens:
            t.undeclare()
        session.close()
        svc.stop()
        cluster.close()
    equal = all(len(g["poses"]) == len(frames) and np.array_equal(g["poses"], alone) for g in got.values())
    worst = max(g["s"] for g in got.values())
    fake = [o for o in owners if o.startswith("fake")]
    emit("fake_tokens", mode=deploy().name, tokens=n, replay_s=round(worst, 1), alone_s=round(alone_s, 1),
         lease_owners=owners, codes={s: g["codes"] for s, g in got.items()})  # fmt: skip
    goal("fake worker tokens: every replay all its poses, equal to offline, within 3x, no lease to a fake worker",
         equal and worst <= 3 * alone_s and not fake, ratio=round(worst / alone_s, 2), fake_owners=len(fake))  # fmt: skip
