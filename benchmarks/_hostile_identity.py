"""Hostile-client steps on identity (benchmarks/hostile_clients.py): sybil ids, a copied id, takeover of an idle
stream, the query budget under a copied id, a session without credentials. Each attacker comes without credentials,
with its own login or with another user's (_hostile_deploy.py), never with the victim's."""

from __future__ import annotations

import threading
import time

import numpy as np
import zenoh
from _hostile_common import BLOCK, emit, goal, run_replay
from _hostile_deploy import deploy

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_services.client import OccVOClient, ServiceError, camera_frame_of
from occvo_services.commands.replay import replay
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import NoRouterError

IDLE_S = max(WorkerConfig.load(f"deploy/{w}.json5").idle_stream_s for w in ("inference_worker", "registration_worker"))


def stored(c) -> np.ndarray:
    """The stream's stored poses (none: an empty array; an attacker may have left it so)."""
    try:
        return c.trajectory().poses.to_numpy()
    except ServiceError:
        return np.zeros((0, 4, 4))


def replay_or_stall(c, frames) -> dict:
    """replay's summary, or for a replay that stalled (no pose for 120 s: locked out) the poses it got."""
    try:
        return replay(c, frames, window=4, timeout=120)
    except ServiceError:
        return {"poses": len(c.poses), "stalled": True}


def victim_replay(ep: str, stream: str, frames) -> dict:
    """The victim's replay (its own login, picked up): time, poses, stored trajectory, the errors on its frames."""
    with OccVOClient(ep, stream, timeout=120) as c:
        t0 = time.perf_counter()
        out = replay_or_stall(c, frames)
        took = time.perf_counter() - t0
        poses = np.array([c.poses[i].matrix() for i in sorted(c.poses)]) if c.poses else np.zeros((0, 4, 4))
        traj = stored(c)
        errors = sorted({(e.code, e.seq) for e in c.errors if e.seq is not None and e.seq < len(frames)})
    return {"s": took, "poses": poses, "n": out["poses"], "traj": traj, "errors": errors}


def solo_s(ep: str, frames, step: str) -> float:
    """The victim's replay alone just before an attack (this host's load drifts: the ratio is side by side)."""
    return run_replay(ep, f"solo{step}", frames)[0]


def _verdict(step: str, got: dict, alone: np.ndarray, alone_s: float, frames, **extra) -> None:
    equal = bool(got["n"] == len(frames) and np.array_equal(got["poses"], alone))
    kept = bool(np.array_equal(got["traj"], alone))
    ratio = got["s"] / alone_s
    emit(step, mode=deploy().name, replay_s=round(got["s"], 2), ratio_to_alone=round(ratio, 2), poses=got["n"],
         poses_equal=equal, stored_equal=kept, victim_errors=got["errors"][:8], **extra)  # fmt: skip
    goal(f"{step}: the victim's replay gets {len(frames)} of {len(frames)} poses equal to offline, stored, within 3x",
         equal and kept and ratio <= 3.0, poses=got["n"], ratio=round(ratio, 2))  # fmt: skip


def no_credentials(ep: str) -> None:
    """A session without credentials: refused by the default's router (anonymous: let in)."""
    try:
        s, _ = deploy().attacker(ep, "none")
        s.close()
        refused = False
    except NoRouterError:
        refused = True
    emit("no_credentials", mode=deploy().name, refused=refused)
    goal("a session without credentials is refused", refused)


def borrowed_ids(ep: str, n: int, who: str = "own") -> list:
    """The ids of n sessions the attacker opened (and closed): ids it may declare as its frames' source."""
    out = []
    for _ in range(n):
        s, _ = deploy().attacker(ep, who)
        out.append(s.id)
        s.close()
    return out


def sybil(ep: str, frames, alone: np.ndarray, alone_s: float, n: int = 64) -> None:
    """One attacker (its own login) putting a frame every 2 s on n stream ids, each frame under another borrowed id,
    beside the victim's replay."""
    alone_s = solo_s(ep, frames, "sybil")
    session, login = deploy().attacker(ep, "own")
    ids = borrowed_ids(ep, n)
    streams = [deploy().wire(f"sybil{i}", login) for i in range(n)]
    payloads = [(keys.camera(s), encode(camera_frame_of(frames[0], s, 0))) for s in streams]
    stop = threading.Event()

    def grab():
        sn = 0
        while not stop.is_set():
            t0 = time.monotonic()
            for (key, data), zid in zip(payloads, ids):
                sn += 1
                session.put(key, data, congestion_control=BLOCK, source_info=zenoh.SourceInfo(zid, sn))
            stop.wait(max(0.0, 2.0 - (time.monotonic() - t0)))

    t = threading.Thread(target=grab)
    t.start()
    time.sleep(5.0)  # the sybil streams admitted (or refused)
    try:
        got = victim_replay(ep, "legitsybil", frames)
    finally:
        stop.set()
        t.join()
        session.close()
    _verdict("sybil", got, alone, alone_s, frames, sybil_ids=n)
    time.sleep(IDLE_S + 15.0)  # the sybil streams retired (idle_stream_s): the next step finds the worker as before


def copied_id(ep: str, frames, alone: np.ndarray, alone_s: float, who: str = "other") -> None:
    """The victim's session id copied (from its camera frames where the attacker can subscribe to them; else handed
    over, as if leaked): the attacker (a login another user owns) puts other frames on the victim's stream under
    that id, seq 0 to 39 over and over, while the victim replays."""
    alone_s = solo_s(ep, frames, "copy")
    stream = deploy().victim_stream("legitcopy")
    session, _ = deploy().attacker(ep, who)
    ear, _ = deploy().attacker(ep, who)  # a session of its own: a session hears its own puts
    seen = []
    sub = ear.declare_subscriber(
        keys.camera(stream), lambda s: seen.append(s.source_info.source_id) if s.source_info else None
    )
    stray = [encode(camera_frame_of(frames[(i + 7) % len(frames)], stream, i)) for i in range(len(frames))]
    stop = threading.Event()
    with OccVOClient(ep, "legitcopy", timeout=120) as c:
        leaked = c.session.id

        def takeover():
            sn = 0
            while not stop.is_set():
                for data in stray:
                    sn += 1
                    zid = seen[0] if seen else leaked
                    session.put(
                        keys.camera(stream), data, congestion_control=BLOCK, source_info=zenoh.SourceInfo(zid, sn)
                    )
                    if stop.wait(0.05):
                        return

        t = threading.Thread(target=takeover)
        t.start()
        try:
            t0 = time.perf_counter()
            out = replay_or_stall(c, frames)
            took = time.perf_counter() - t0
        finally:
            stop.set()
            t.join()
        poses = np.array([c.poses[i].matrix() for i in sorted(c.poses)]) if c.poses else np.zeros((0, 4, 4))
        time.sleep(1.0)
        got = {"s": took, "poses": poses, "n": out["poses"], "traj": stored(c),
               "errors": sorted({(e.code, e.seq) for e in c.errors if e.seq is not None})}  # fmt: skip
    sub.undeclare()
    ear.close()
    session.close()
    _verdict("copied_id", got, alone, alone_s, frames, attacker=who, id_seen_by_subscribing=bool(seen))


def takeover_idle(ep: str, frames, alone: np.ndarray, stream: str = "legit0", who: str = "other") -> None:
    """The victim's stream `stream` idle (retired, stored): the attacker puts seq 0 of another frame, then 1 to 5,
    on it. The victim's stored trajectory and map before and after."""
    with OccVOClient(ep, stream, timeout=60) as c:
        before, info0 = stored(c), c.map_info()
        wire = c.stream
    session, _ = deploy().attacker(ep, who)
    for i in range(6):
        data = encode(camera_frame_of(frames[(i + 7) % len(frames)], wire, i))
        session.put(keys.camera(wire), data, congestion_control=BLOCK, source_info=zenoh.SourceInfo(session.id, i + 1))
        time.sleep(0.3)
    time.sleep(5.0)
    session.close()
    with OccVOClient(ep, stream, timeout=60) as c:
        after, info1 = stored(c), c.map_info()
    same = bool(np.array_equal(after, before))
    same_map = info1.voxel_count == info0.voxel_count and info1.last_seq == info0.last_seq
    equal = bool(np.array_equal(after, alone))
    emit("takeover", mode=deploy().name, attacker=who, stored_before=len(before), stored_after=len(after),
         trajectory_unchanged=same, map_unchanged=same_map, map_last_seq=[info0.last_seq, info1.last_seq])  # fmt: skip
    goal("takeover of an idle stream: its stored trajectory and map unchanged, equal to offline",
         same and same_map and equal, stored_after=len(after))  # fmt: skip


def query_budget(ep: str, frames, stream: str = "legit0", who: str = "own") -> None:
    """The victim's id copied: 10 attacker threads loop tile queries under it, on the victim's stream (refused by the
    access control in the default) and on the attacker's own stream, while the victim asks 200 tiles one by one:
    the victim's gets refused busy."""
    session, login = deploy().attacker(ep, who)
    own = deploy().wire("qown", login)
    with OccVOClient(ep, own, timeout=120, session=session, login=login) as mine:
        mine.reset()
        for f in frames[:3]:
            mine.step(f)
        time.sleep(2.0)
        jx, jy = mine.map_info().tiles[0]
    with OccVOClient(ep, stream, timeout=60) as c:
        ix, iy = c.map_info().tiles[0]
        leaked, victim_sel = c.session.id, keys.map_tile(c.stream, ix, iy)
        stop, counts = threading.Event(), {"answered": 0, "busy": 0}

        def hammer(sel):
            sn = 0
            while not stop.is_set():
                sn += 1
                info = zenoh.SourceInfo(leaked, 2_000_000 + sn)
                for r in session.get(sel, timeout=5.0, target=zenoh.QueryTarget.BEST_MATCHING, source_info=info):
                    counts["busy" if r.err is not None else "answered"] += 1

        sels = [victim_sel] * 5 + [keys.map_tile(own, jx, jy)] * 5
        ts = [threading.Thread(target=hammer, args=(s,)) for s in sels]
        for t in ts:
            t.start()
        times, refused = [], 0
        for k in range(200):
            t0 = time.perf_counter()
            info = zenoh.SourceInfo(c.session.id, 1_000_000 + k)
            replies = list(
                c.session.get(victim_sel, timeout=5.0, target=zenoh.QueryTarget.BEST_MATCHING, source_info=info)
            )
            times.append((time.perf_counter() - t0) * 1000)
            refused += sum(1 for r in replies if r.err is not None)
        stop.set()
        for t in ts:
            t.join()
    session.close()
    emit("query_budget", mode=deploy().name, attacker=who, victim_gets=200, victim_refused=refused,
         victim_tile_p50_p99_ms=np.percentile(times, [50, 99]).round(1).tolist(), attacker_replies=counts)  # fmt: skip
    goal("queries under a copied id do not use up the victim's query budget", refused == 0, refused=refused)
