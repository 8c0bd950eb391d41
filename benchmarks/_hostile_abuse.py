"""Hostile-client steps of sequence, admission, query and log abuse (benchmarks/hostile_clients.py)."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import zenoh
from _hostile_common import (
    BLOCK,
    counters,
    emit,
    goal,
    grab,
    run_replay,
)
from _hostile_deploy import deploy

from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import PoseEstimate
from occvo_services.client import OccVOClient, ServiceError, camera_frame_of
from occvo_services.commands.replay import replay
from occvo_services.logins import login_of
from occvo_services.runtime import WorkerConfig


def sequence_abuse(ep: str, frames, alone: np.ndarray, alone_s: float) -> None:
    """A replay while its own client puts a stray seq 99,999 and duplicates, and another session pre-empts it."""
    stream = deploy().victim_stream("legit4")  # the other session: the attacker's own login
    hostile, _ = deploy().attacker(ep, "own")
    stray = [encode(camera_frame_of(frames[(i + 7) % len(frames)], stream, i)) for i in range(len(frames))]
    far = encode(camera_frame_of(frames[5], stream, 99_999))
    sn = [0]

    def preempt(sample):  # seq k+1 as soon as pose k is out, and a seq 99,999 once
        k = decode(sample.payload.to_bytes(), PoseEstimate).seq
        for payload in ([stray[k + 1]] if k + 1 < len(stray) else []) + ([far] if k == 1 else []):
            sn[0] += 1
            if hostile.is_closed():
                return
            hostile.put(
                keys.camera(stream), payload, congestion_control=BLOCK, source_info=zenoh.SourceInfo(hostile.id, sn[0])
            )

    sub = hostile.declare_subscriber(keys.pose(stream), preempt)
    time.sleep(0.5)
    stop = threading.Event()
    with OccVOClient(ep, "legit4", timeout=300) as c:

        def own_abuse():  # the client's own session: a stray seq 99,999 after pose 1, an exact duplicate of each frame
            sent = 0
            while not stop.wait(0.01):
                done = sorted(c.poses)
                if 1 in done and sent == 0:
                    c.put_encoded(far)
                while sent < len(done):
                    c.put_encoded(encode(camera_frame_of(frames[done[sent]], stream, done[sent])))
                    sent += 1

        abuser = threading.Thread(target=own_abuse)
        abuser.start()
        t0 = time.perf_counter()
        out = replay(c, frames, window=4, timeout=600)
        took = time.perf_counter() - t0
        stop.set()
        abuser.join()
        poses = np.array([c.poses[i].matrix() for i in sorted(c.poses)])
        traj = c.trajectory()
        own_errors = [(e.code, e.seq) for e in c.errors if e.seq is not None and e.seq < len(frames)]
    sub.undeclare()
    hostile.close()
    equal = bool(out["poses"] == len(frames) and np.array_equal(poses, alone))
    stored = bool(
        np.array_equal(traj.poses.to_numpy(), alone) and traj.seqs.to_numpy().tolist() == list(range(len(frames)))
    )
    emit(
        "sequence",
        mode=deploy().name,
        replay_s=round(took, 2),
        ratio_to_alone=round(took / alone_s, 2),
        poses=out["poses"],
        poses_equal=equal,
        stored_trajectory_equal=stored,
        errors_on_own_frames=own_errors,
    )
    goal(
        "seq 99,999 and pre-emption leave the trajectory equal to offline",
        equal and stored,
        poses_equal=equal,
        stored_trajectory_equal=stored,
    )
    goal(
        "duplicates and another client's frames give the replay's client no error",
        not own_errors,
        errors=len(own_errors),
    )


def grabber(ep: str, frames, alone_s: float, groups: list[list[str]], stream: str, label: str, logins=None) -> dict:
    """A replay of `stream` beside grabbers (one session each, holding `groups` of stream ids). `logins`: the zenoh
    config of each grabber's session, then the replay's (ACL users), and a function of the service's state before
    the replay, whose fields are printed too."""
    if logins is None:  # the grabbers: the attacker's own login (in the default), its prefix on their ids
        own = deploy().config("own")
        groups = [[deploy().wire(s, login_of(own)) for s in g] for g in groups]
    bases, base, state = logins or ([own] * len(groups), None, dict)
    stop = threading.Event()
    ts = [threading.Thread(target=grab, args=(ep, ids, frames[0], stop, 2.0, b)) for ids, b in zip(groups, bases)]
    for t in ts:
        t.start()
    time.sleep(5.0)  # their streams admitted (the rest refused)
    try:
        before = state()
        took, poses = run_replay(ep, stream, frames, base)
    finally:
        stop.set()
        for t in ts:
            t.join()
    ratio = took / alone_s
    emit(
        "grabber",
        mode=label,
        deployment=deploy().name,
        grabbed_ids=sum(map(len, groups)),
        **before,
        replay_s=round(took, 2),
        alone_s=round(alone_s, 2),
        ratio_to_alone=round(ratio, 2),
        poses=len(poses),
    )
    goal(
        f"a replay beside a slot grabber ({label}) gets all its poses within 3x its solo time",
        len(poses) == len(frames) and ratio <= 3.0,
        ratio=round(ratio, 2),
        poses=len(poses),
    )
    return {"ratio": ratio}


def silent_queryable(ep: str, stream: str) -> None:
    """A queryable on occvo/** that never answers (its queries held open), and another session looping tile queries
    named with `stream`: the stream's client's query times, and its gets refused busy."""
    held, (rogue, _) = [], deploy().attacker(ep, "own")
    queryable = rogue.declare_queryable("occvo/**", held.append)  # held: never answered until their timeout
    time.sleep(0.5)
    with OccVOClient(ep, stream, timeout=60) as c, OccVOClient(ep, "nosuchstream", timeout=60) as nobody:
        ix, iy = c.map_info().tiles[0]
        asks = {
            "tile": lambda: c.tile(ix, iy),
            "map_info": c.map_info,
            "trajectory": c.trajectory,
            "pose_latest": c.pose_latest,
            "stats": c.stats,  # every worker's answer (occvo/** does not match the @workers chunk)
            "unknown_stream_trajectory": lambda: nobody.trajectory(),  # no answer but errors: waits for the rogue
        }
        took = {}
        for name, ask in asks.items():
            times = []
            for _ in range(3 if name.startswith("unknown") else 20):
                t = time.perf_counter()
                try:
                    ask()
                except ServiceError:  # the unknown stream's: its error replies, after the query timeout
                    pass
                times.append(time.perf_counter() - t)
            took[name] = round(max(times), 3)
        stop, hostile_busy = threading.Event(), [0]
        hostile, _ = deploy().attacker(ep, "own")
        sel = keys.map_tile(c.stream, ix, iy)

        def hammer():
            while not stop.is_set():
                for r in hostile.get(sel, timeout=5.0, target=zenoh.QueryTarget.BEST_MATCHING):
                    if r.err is not None:
                        hostile_busy[0] += 1

        ts = [threading.Thread(target=hammer) for _ in range(10)]
        for t in ts:
            t.start()
        victim, refused = [], 0
        for k in range(200):  # one get each, as the stream's client's session, not asked again on busy
            t = time.perf_counter()
            info = zenoh.SourceInfo(c.session.id, 1_000_000 + k)
            replies = list(c.session.get(sel, timeout=5.0, target=zenoh.QueryTarget.BEST_MATCHING, source_info=info))
            victim.append((time.perf_counter() - t) * 1000)
            refused += sum(1 for r in replies if r.err is not None)
        stop.set()
        for t in ts:
            t.join()
        hostile.close()
    queryable.undeclare()
    held.clear()
    rogue.close()
    worst = max(v for k, v in took.items())
    emit(
        "silent",
        mode=deploy().name,
        query_timeout_s=2.0,
        max_query_s_with_a_silent_queryable=took,
        victim_tile_p50_p99_ms=np.percentile(victim, [50, 99]).round(1).tolist(),
        victim_gets_refused=refused,
        hostile_gets_refused=hostile_busy[0],
    )
    goal("a silent queryable costs a query at most its timeout (2 s)", worst <= 2.2, worst_s=worst)
    goal("querying a victim's stream name does not use up its query budget", refused == 0, refused=refused)


def degenerate_frames(ep: str, frames) -> None:
    """One voxel, three collinear voxels and an all-zero coordinate table after 3 real frames, then real ones."""
    from occvo_core.frame import OccupancyFrame
    from occvo_schemas.models import Array

    f = frames[3]
    zero = camera_frame_of(frames[5], "legit7", 5)
    occ = zero.gt_occupancy
    zero = zero.model_copy(
        update={"gt_occupancy": occ.model_copy(update={"axes": Array.from_numpy(np.zeros(occ.axes.shape))})}
    )
    line = np.array([[0.2, 0.2, 0.2], [1.0, 0.2, 0.2], [1.8, 0.2, 0.2]])
    bad = [OccupancyFrame(f.points[:1], f.labels[:1], 3, f.stamp), OccupancyFrame(line, f.labels[:3], 4, f.stamp), zero]
    with OccVOClient(ep, "legit7", timeout=120) as c:
        c.reset()
        got = [c.step(x) for x in [*frames[:3], *bad, *frames[6:8]]]
    statuses = [p.status for p in got]
    p1, p2 = got[1].matrix(), got[2].matrix()
    velocity = bool(np.allclose(got[3].matrix(), p2 @ np.linalg.inv(p1) @ p2, atol=1e-9))
    emit("degenerate", statuses=statuses, constant_velocity_pose=velocity)
    goal("degenerate frames say so, with a constant-velocity pose", statuses[3:6] == ["degenerate"] * 3 and velocity)


def log_flood(ep: str, svc, seconds: float = 10.0) -> None:
    """One session putting 1-byte payloads on distinct keys for `seconds`: the error log lines the inference worker
    writes (errors less errors_suppressed), each line under ~700 bytes."""
    session, login = deploy().attacker(ep, "own")
    names = ("errors", "errors_suppressed")
    before = counters(session, svc, "inference", names)
    t0, n = time.perf_counter(), 0
    while time.perf_counter() - t0 < seconds:
        n += 1
        session.put(
            f"occvo/{deploy().wire(f'flood{n}', login)}/camera",
            b"\x01",
            congestion_control=BLOCK,
            source_info=zenoh.SourceInfo(session.id, n),
        )
    deadline = time.perf_counter() + 60.0  # the puts queued at the worker all handled: its error count settles
    after, elapsed = counters(session, svc, "inference", names), time.perf_counter() - t0
    while time.perf_counter() < deadline:  # elapsed: when the count was last seen still moving (or first final)
        time.sleep(2.0)
        again = counters(session, svc, "inference", names)
        if again == after:
            break
        after, elapsed = again, time.perf_counter() - t0
    session.close()
    lines = (after["errors"] - before["errors"]) - (after["errors_suppressed"] - before["errors_suppressed"])
    config = WorkerConfig.load("deploy/inference_worker.json5")
    bound = config.error_burst + config.error_events_per_s * elapsed  # a token bucket over the time it was used
    emit("log_flood", mode=deploy().name, seconds=seconds, puts=n, handled_within_s=round(elapsed, 1),
         log_lines=lines, log_mb_at_700_bytes_a_line=round(lines * 700 / 1e6, 3))  # fmt: skip
    goal(
        "one client's 1-byte puts on distinct keys log at most its error budget (and under 10 MB)",
        lines <= bound + 5 and lines * 700 < 10e6,
        lines=lines,
        bound=round(bound),
    )


def msgpack_delay(ep: str, frames) -> None:
    """A 13.7 MB payload of small maps between a stream's two frames (the attacker's, on a stream of its own: the
    access control keeps it off the victim's): the second frame's round trip vs without it."""
    session, login = deploy().attacker(ep, "own")
    hostile = msgpack.packb(
        {
            "kind": "camera_frame",
            "schema_version": 1,
            "stream": "legit2h0",
            "x": [[{"a": 1, "b": 2} for _ in range(60000)] for _ in range(35)],
        }
    )

    def second_frame_ms(stream: str, hostile_between: bool) -> float:
        with OccVOClient(ep, stream, timeout=120) as c:
            c.reset()
            c.step(frames[0])
            if hostile_between:
                session.put(keys.camera(deploy().wire(stream, login)), hostile, congestion_control=BLOCK)
            t = time.perf_counter()
            c.step(frames[1])
            return (time.perf_counter() - t) * 1000

    plain_ms = float(np.median([second_frame_ms(f"legit2p{i}", False) for i in range(3)]))
    after_ms = float(np.median([second_frame_ms(f"legit2h{i}", True) for i in range(3)]))
    session.close()
    emit(
        "msgpack",
        mode=deploy().name,
        payload_mb=round(len(hostile) / 1e6, 1),
        frame_ms_alone=round(plain_ms, 1),
        frame_ms_after_hostile=round(after_ms, 1),
        delay_ms=round(after_ms - plain_ms, 1),
    )
