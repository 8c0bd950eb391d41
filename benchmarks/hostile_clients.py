"""A hostile client beside a legitimate replay, on loopback: the figures of issue 33's "done when".

    python benchmarks/hostile_clients.py [--streams 2000 --flood-s 10 --settle-s 60 --big-mb 512]
        [--steps flood,msgpack,oversize,queries] [--registration-max-rss-mb MB]

Router in this process, workers as processes (occvo_services.local.LocalService, the deploy configs' limits). Steps:
  alone      scene-0101 replayed alone: time, poses; each worker's RSS and threads once its stream has retired
             (baseline: the service at rest)
  flood      one client puts a seq-0 frame on each of --streams stream ids in --flood-s seconds while scene-0101 is
             replayed: replay time vs alone, poses equal, registration RSS peak against its max_rss_mb, streams
             refused (by the stream limits, by the memory cap) and evicted; --settle-s after the flood: every
             worker's RSS and threads vs baseline, idle CPU
  msgpack    a 13.7 MB payload of small maps, then a legitimate frame: that frame's round trip vs one sent alone
  oversize   a --big-mb MiB put: RSS rise of the router (this process) and of each worker
  queries    ten concurrent gets on occvo/** beside a tile query loop: its p50/p99 vs alone, the gets refused busy
  sequence   a replay while its own client puts a stray seq 99,999 and exact duplicates of its frames, and another
             session puts seq k+1 (and a seq 99,999) on it as soon as it sees pose k: poses and stored trajectory vs
             alone, errors the replay's client got for its own frames
  grabber    one session holding 50 stream ids (a frame on each every 2 s) beside a replay: replay time vs alone, all
             poses; then a service with client_identity "user" (the ACL's rule) and 4 users holding 16 ids each
             (max_streams 64 full) beside a replay of a fifth: the same figures
  silent     a queryable on occvo/** that never answers: the longest of 20 tile, map info, trajectory, pose and
             stats queries, and of 3 trajectory queries of an unknown stream (only errors come: the query waits for
             the rogue until its timeout); another session looping tile queries named
             with the replay's stream: that stream's client's tile query p50/p99 and its gets refused busy
  degenerate one voxel, three collinear voxels and an all-zero coordinate table among real frames: their statuses,
             whether the first has the constant-velocity pose
  log_flood  one session putting 1-byte payloads on distinct keys for 10 s: the inference worker's error log lines
  config     `occvo serve` with each bad configuration of the issue: exit codes and stderr lines
  disk_full  (with --disk-full-dir, a small filesystem) the store's filesystem filled for --full-s seconds after
             pose 10 of a replay: every pose vs alone, the frames refused not_stored, the map vs alone's
  heavy      a service whose registration worker is capped at --heavy-max-rss-mb: 4 clients each put a frame of
             3.5 M copies of one voxel then --heavy-frames full-grid frames (640,000 voxels) beside a replay: the
             registration worker's RSS peak against its cap, frames refused, the replay's time vs its solo time
`alone` always runs (the baseline and the map the queries ask for); --steps picks the others. Prints one JSON line
per step and one per goal ({"goal": ..., "met": ...}); exits 1 if a goal is not met."""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import msgpack
import numpy as np
import zenoh
from _common import SAMPLE

from occvo_core.datasets import OccVOReleaseScene
from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import ErrorEvent, PoseEstimate, WorkerHealth
from occvo_services.client import OccVOClient, ServiceError, camera_frame_of
from occvo_services.commands.replay import replay
from occvo_services.local import LocalService
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import open_session

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


def counters(session, svc, role: str, names: tuple[str, ...]) -> dict:
    """Some of a worker's counters, from its stats queryable (LocalService names it <role>-<our pid>)."""
    for r in session.get(keys.stats(f"{role}-{os.getpid()}"), timeout=10.0):
        if r.ok is not None:
            got = decode(r.ok.payload.to_bytes(), WorkerHealth).counters
            return {n: got.get(n, 0) for n in names}
    return {}


def wildcard_gets(endpoint: str, threads: int, stop, counts) -> None:
    """A client looping `occvo/**` gets on `threads` threads until `stop`; counts[0] ok replies, counts[1] busy."""
    session = open_session(endpoint)

    def loop():
        while not stop.is_set():
            for r in session.get("occvo/**", timeout=10.0):
                busy = r.err is not None and decode(r.err.payload.to_bytes(), ErrorEvent).code == "busy"
                with counts.get_lock():
                    counts[int(busy)] += 1

    ts = [threading.Thread(target=loop) for _ in range(threads)]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    session.close()


def emit(step: str, **fields) -> None:
    print(json.dumps({"step": step, **fields}), flush=True)


GOALS: list[bool] = []


def goal(text: str, met: bool, **figure) -> None:
    GOALS.append(bool(met))
    print(json.dumps({"goal": text, "met": bool(met), **figure}), flush=True)


def grab(endpoint: str, streams: list[str], frame, stop: threading.Event, period_s: float = 2.0) -> None:
    """A slot grabber: one session putting a seq-0 frame on each of `streams` every period_s until stop."""
    session = open_session(endpoint)
    payloads = [(keys.camera(s), encode(camera_frame_of(frame, s, 0))) for s in streams]
    sn = 0
    while not stop.is_set():
        t0 = time.monotonic()
        for key, payload in payloads:
            sn += 1
            session.put(key, payload, congestion_control=BLOCK, source_info=zenoh.SourceInfo(session.id, sn))
        stop.wait(max(0.0, period_s - (time.monotonic() - t0)))
    session.close()


def sequence_abuse(ep: str, frames, alone: np.ndarray, alone_s: float) -> None:
    """A replay while its own client puts a stray seq 99,999 and duplicates, and another session pre-empts it."""
    stream = "legit4"
    hostile = open_session(ep)
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
    with OccVOClient(ep, stream, timeout=300) as c:

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


def heavy(args, frames, store: list[str], reg_config: str) -> None:
    """Heavy frames on 4 streams beside a replay, the registration worker capped at --heavy-max-rss-mb: a frame of
    3.5 M copies of one voxel (refused: more voxels than the grid's cells) then full-grid frames (640,000 voxels)."""
    from occvo_core.grid import OCC3D_GRID
    from occvo_schemas.models import CameraFrame, SparseOccupancy

    cap = args.heavy_max_rss_mb
    svc = LocalService(
        quiet=True,
        worker_args={
            "registration": ["--config", reg_config, *store, "--max-rss-mb", str(cap)],
            "inference": ["--config", "deploy/inference_worker.json5"],
            "map": ["--config", "deploy/map_service.json5", *store],
        },
    ).start()
    try:
        ep = svc.endpoint
        solo_s, _ = run_replay(ep, "heavysolo", frames)
        idx = np.indices(OCC3D_GRID.shape).reshape(3, -1).T.astype(np.uint8)
        labels = np.random.default_rng(0).integers(1, 17, len(idx)).astype(np.uint8)

        full = {
            "voxels": {"dtype": "uint8", "shape": [len(idx), 3], "data": idx.tobytes()},
            "labels": {"dtype": "uint8", "shape": [len(idx)], "data": labels.tobytes()},
        }
        n = 3_500_000
        copies = {
            "voxels": {"dtype": "uint8", "shape": [n, 3], "data": bytes(3 * n)},
            "labels": {"dtype": "uint8", "shape": [n], "data": bytes(n)},
        }
        template = msgpack.unpackb(
            encode(CameraFrame(stream="x", seq=0, stamp=0.0, gt_occupancy=SparseOccupancy.model_validate(full))),
            raw=False,
        )

        def payload(stream, seq, occ):
            d = dict(template, stream=stream, seq=seq, stamp=float(seq) * 0.5)
            d["gt_occupancy"] = {**template["gt_occupancy"], **occ}
            return msgpack.packb(d, use_bin_type=True)

        peak, stop = {"rss_mb": 0.0}, threading.Event()

        def watch():
            while not stop.wait(0.05):
                peak["rss_mb"] = max(peak["rss_mb"], proc_status(svc.procs["registration"].pid)["rss_mb"])

        def heavy_client(i):
            session, stream = open_session(ep), f"heavy{i}"
            for sn, data in enumerate(
                [payload(stream, 0, copies)] + [payload(stream, s, full) for s in range(args.heavy_frames)]
            ):
                session.put(
                    keys.camera(stream),
                    data,
                    congestion_control=BLOCK,
                    source_info=zenoh.SourceInfo(session.id, sn + 1),
                )
            session.close()

        threading.Thread(target=watch, daemon=True).start()
        clients = [threading.Thread(target=heavy_client, args=(i,)) for i in range(4)]
        for t in clients:
            t.start()
        took, poses = run_replay(ep, "heavylegit", frames)
        for t in clients:
            t.join()
        time.sleep(5.0)  # the heavy frames queued are registered
        stop.set()
        session = open_session(ep)
        refused = counters(
            session, svc, "registration", ("frames_refused_memory", "streams_refused_memory", "frames_out", "errors")
        )
        refused_inf = counters(session, svc, "inference", ("errors",))
        session.close()
        emit(
            "heavy",
            registration_max_rss_mb=cap,
            registration_peak_rss_mb=peak["rss_mb"],
            replay_s=round(took, 2),
            solo_s=round(solo_s, 2),
            ratio_to_solo=round(took / solo_s, 2),
            poses=len(poses),
            registration=refused,
            inference=refused_inf,
        )
        goal(
            "heavy-frame streams keep the registration worker's RSS under max_rss_mb",
            peak["rss_mb"] < cap,
            peak_rss_mb=peak["rss_mb"],
            cap=cap,
        )
    finally:
        svc.stop()


def silent_queryable(ep: str, stream: str) -> None:
    """A queryable on occvo/** that never answers (its queries held open), and another session looping tile queries
    named with `stream`: the stream's client's query times, and its gets refused busy."""
    held, rogue = [], open_session(ep)
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
        hostile = open_session(ep)
        sel = keys.map_tile(stream, ix, iy)

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
        query_timeout_s=2.0,
        max_query_s_with_a_silent_queryable=took,
        victim_tile_p50_p99_ms=np.percentile(victim, [50, 99]).round(1).tolist(),
        victim_gets_refused=refused,
        hostile_gets_refused=hostile_busy[0],
    )
    goal("a silent queryable costs a query at most its timeout (2 s) in the plain default", worst <= 2.2, worst_s=worst)
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


def bad_configs() -> None:
    """`occvo serve` with each bad configuration the issue found: one line on stderr, exit code 2, in seconds."""
    import json5

    tmp = Path(tempfile.mkdtemp())
    lan = "tcp/0.0.0.0:17447"
    cases = {}
    for name, setting in {
        "tile_m 1.0": {"tile_m": 1.0},
        "tile_m 0.001": {"tile_m": 0.001},
        "max_rss_mb 64": {"max_rss_mb": 64},
        "kernel_threads 100000": {"kernel_threads": 100000},
    }.items():
        d = tmp / name.replace(" ", "_")
        d.mkdir()
        for f in ("inference_worker.json5", "registration_worker.json5", "map_service.json5"):
            data = json5.loads((Path("services/defaults") / f).read_text())
            data.update(setting if f.startswith("registration") else {})
            (d / f).write_text(json.dumps(data))
        cases[name] = ["--config-dir", str(d), "--listen", "tcp/127.0.0.1:17448"]
    (tmp / "router.json5").write_text(
        json.dumps({"mode": "router", "listen": {"endpoints": ["tcp/127.0.0.1:17449", lan]}})
    )
    cases["loopback then LAN endpoint"] = ["--router-config", str(tmp / "router.json5")]
    (tmp / "auth.json5").write_text(
        json.dumps(
            {
                "mode": "router",
                "listen": {"endpoints": [lan]},
                "transport": {"auth": {"usrpwd": {"dictionary_file": str(tmp / "users.txt")}}},
            }
        )
    )
    (tmp / "users.txt").write_text("a:b\n")
    cases["authentication without access control"] = ["--router-config", str(tmp / "auth.json5")]
    cases["store folder missing"] = ["--store", str(tmp / "no" / "x.sqlite")]
    results = {}
    for name, argv in cases.items():
        t = time.perf_counter()
        r = subprocess.run(
            [sys.executable, "-m", "occvo_cli", "serve", *argv], capture_output=True, text=True, timeout=120
        )
        lines = [line for line in r.stderr.splitlines() if line.strip()]
        results[name] = {"exit": r.returncode, "stderr_lines": len(lines), "s": round(time.perf_counter() - t, 1)}
    emit("config", cases=results)
    ok = all(v["exit"] == 2 and v["stderr_lines"] == 1 for v in results.values())
    goal("every bad configuration is one line and exit code 2", ok, cases=len(results))


def disk_full(args, frames, alone: np.ndarray, reg_config: str) -> None:
    """A service whose store is on --disk-full-dir (a small filesystem, e.g. a tmpfs): after pose 10 of a replay the
    filesystem is filled for --full-s seconds, then freed. Every pose vs alone, the map's last seq and tiles."""
    folder = Path(args.disk_full_dir)
    store = ["--store-path", str(folder / f"occvo-{os.getpid()}.sqlite")]
    svc = LocalService(
        quiet=True,
        worker_args={
            "registration": ["--config", reg_config, *store],
            "inference": ["--config", "deploy/inference_worker.json5"],
            "map": ["--config", "deploy/map_service.json5", *store],
        },
    ).start()
    filler = folder / f"filler-{os.getpid()}"
    spell = {}
    try:
        with OccVOClient(svc.endpoint, "full", timeout=600, resend_after=1.0) as c:

            def fill():
                with c._cv:
                    c._cv.wait_for(lambda: 10 in c.poses, 300)
                with open(filler, "wb") as f:
                    try:
                        while True:
                            f.write(b"\0" * (1 << 20))
                            f.flush()
                    except OSError:
                        pass
                spell["filled_at"] = time.perf_counter()
                time.sleep(args.full_s)
                filler.unlink()
                spell["freed_at"] = time.perf_counter()

            t = threading.Thread(target=fill)
            t.start()
            t0 = time.perf_counter()
            out = replay(c, frames, window=4, timeout=600)
            took = time.perf_counter() - t0
            t.join()
            poses = np.array([c.poses[i].matrix() for i in sorted(c.poses)])
            refused = sorted({e.seq for e in c.errors if e.code == "not_stored"})
            deadline = time.monotonic() + 60
            while (info := c.map_info()).last_seq != len(frames) - 1 and time.monotonic() < deadline:
                time.sleep(0.5)
        emit(
            "disk_full",
            full_s=args.full_s,
            replay_s=round(took, 2),
            poses=out["poses"],
            poses_equal=bool(np.array_equal(poses, alone)),
            frames_refused_not_stored=refused,
            resends=c.resends,
            map_last_seq=info.last_seq,
            map_tiles=len(info.tiles),
            map_voxels=info.voxel_count,
        )
        goal(
            "after a disk-full spell every pose is there and the map complete",
            out["poses"] == len(frames) and np.array_equal(poses, alone) and info.last_seq == len(frames) - 1,
            refused=len(refused),
        )
        return info
    finally:
        filler.unlink(missing_ok=True)
        svc.stop()


def log_flood(ep: str, svc, seconds: float = 10.0) -> None:
    """One session putting 1-byte payloads on distinct keys for `seconds`: the error log lines the inference worker
    writes (errors less errors_suppressed), each line under ~700 bytes."""
    session = open_session(ep)
    names = ("errors", "errors_suppressed")
    before = counters(session, svc, "inference", names)
    t0, n = time.perf_counter(), 0
    while time.perf_counter() - t0 < seconds:
        n += 1
        session.put(
            f"occvo/flood{n}/camera", b"\x01", congestion_control=BLOCK, source_info=zenoh.SourceInfo(session.id, n)
        )
    time.sleep(2.0)
    after = counters(session, svc, "inference", names)
    session.close()
    lines = (after["errors"] - before["errors"]) - (after["errors_suppressed"] - before["errors_suppressed"])
    config = WorkerConfig.load("deploy/inference_worker.json5")
    bound = config.error_burst + config.error_events_per_s * (seconds + 2.0)
    emit("log_flood", seconds=seconds, puts=n, log_lines=lines, log_mb_at_700_bytes_a_line=round(lines * 700 / 1e6, 3))
    goal(
        "one client's 1-byte puts on distinct keys log at most its error budget (and under 10 MB)",
        lines <= bound + 5 and lines * 700 < 10e6,
        lines=lines,
        bound=bound,
    )


def grabber(ep: str, frames, alone_s: float, groups: list[list[str]], stream: str, label: str) -> dict:
    """A replay of `stream` beside grabbers (one session each, holding `groups` of stream ids)."""
    stop = threading.Event()
    ts = [threading.Thread(target=grab, args=(ep, ids, frames[0], stop)) for ids in groups]
    for t in ts:
        t.start()
    time.sleep(5.0)  # their streams admitted (the rest refused)
    try:
        took, poses = run_replay(ep, stream, frames)
    finally:
        stop.set()
        for t in ts:
            t.join()
    ratio = took / alone_s
    emit(
        "grabber",
        mode=label,
        grabbed_ids=sum(map(len, groups)),
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


def run_replay(endpoint: str, stream: str, frames) -> tuple[float, np.ndarray]:
    with OccVOClient(endpoint, stream, timeout=300) as c:
        t0 = time.perf_counter()
        out = replay(c, frames, window=4, timeout=600)
        took = time.perf_counter() - t0
        poses = np.array([c.poses[i].matrix() for i in sorted(c.poses)]) if c.poses else np.zeros((0, 4, 4))
        codes = sorted({(e.worker.split("-")[0], e.code, e.message[:120]) for e in c.errors})
    assert out["poses"] == len(frames), (out["poses"], out["errors"], codes)
    return took, poses


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--streams", type=int, default=2000)
    p.add_argument("--flood-s", type=float, default=10.0)
    p.add_argument("--settle-s", type=float, default=60.0)
    p.add_argument("--big-mb", type=int, default=512)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument(
        "--steps",
        default="flood,msgpack,oversize,queries,sequence,grabber,heavy,silent,degenerate,config,log_flood,disk_full",
        help="steps after `alone`, comma separated",
    )
    p.add_argument("--disk-full-dir", help="step disk_full: a small filesystem for the store (e.g. a 64 MB tmpfs)")
    p.add_argument("--full-s", type=float, default=5.0, help="step disk_full: how long the filesystem stays full")
    p.add_argument("--heavy-max-rss-mb", type=int, default=1024, help="the registration worker's cap in step heavy")
    p.add_argument("--heavy-frames", type=int, default=5, help="full-grid frames on each of the 4 heavy streams")
    p.add_argument("--registration-max-rss-mb", type=int, help="the registration worker's cap instead of its config's")
    args = p.parse_args()
    steps = set(args.steps.split(","))
    reg_config = "deploy/registration_worker.json5"
    cap = args.registration_max_rss_mb or WorkerConfig.load(reg_config).max_rss_mb
    reg_cap = ["--max-rss-mb", str(cap)] if args.registration_max_rss_mb else []
    scene = OccVOReleaseScene(DATA)
    frames = [scene[i] for i in range(min(args.frames, len(scene)))]
    store = ["--store-path", str(Path(tempfile.mkdtemp()) / "occvo.sqlite")]  # idle streams' state goes there
    svc = LocalService(
        quiet=True,
        worker_args={
            "registration": ["--config", reg_config, *store, *reg_cap],
            "inference": ["--config", "deploy/inference_worker.json5"],
            "map": ["--config", "deploy/map_service.json5", *store],
        },
    ).start()
    try:
        ep = svc.endpoint
        alone_s, alone = run_replay(ep, "legit0", frames)
        with OccVOClient(ep, "legit0", timeout=60) as c:
            deadline = time.monotonic() + 60
            while (alone_info := c.map_info()).last_seq != len(frames) - 1 and time.monotonic() < deadline:
                time.sleep(0.2)
        session = open_session(ep)
        # the flood's baseline is the service at rest: the replay's stream retired (idle_stream_s), as the flood's will be
        deadline = time.monotonic() + WorkerConfig.load(reg_config).idle_stream_s + 60
        while "flood" in steps and counters(session, svc, "registration", ("streams_retired",))["streams_retired"] < 1:
            assert time.monotonic() < deadline, "the replay's stream was not retired"
            time.sleep(1.0)
        base = workers(svc)
        emit("alone", replay_s=round(alone_s, 2), poses=len(alone), workers=base)

        if "flood" in steps:
            peak = {"rss_mb": 0.0}
            stop = threading.Event()

            # encoded before the flood (voxel indices: 0.12 MB each), so that putting them takes --flood-s, not the
            # encoding's time (21.8 s for 2,000 when encoded one by one)
            payloads = [encode(camera_frame_of(frames[0], f"flood{i}", 0, exact=False)) for i in range(args.streams)]

            def flood():
                start = time.perf_counter()
                for i, small in enumerate(payloads):
                    session.put(keys.camera(f"flood{i}"), small, congestion_control=BLOCK)
                    time.sleep(max(0.0, start + (i + 1) * args.flood_s / args.streams - time.perf_counter()))
                peak["put_s"] = time.perf_counter() - start

            def watch():
                while not stop.wait(0.1):
                    peak["rss_mb"] = max(peak["rss_mb"], proc_status(svc.procs["registration"].pid)["rss_mb"])

            threading.Thread(target=watch, daemon=True).start()
            flooder = threading.Thread(target=flood)
            t0 = time.perf_counter()
            flooder.start()
            flood_s, flooded = run_replay(ep, "legit1", frames)
            flooder.join()
            flood_end = time.perf_counter()
            del payloads
            stop.set()
            emit(
                "flood",
                streams=args.streams,
                puts_took_s=round(peak["put_s"], 1),
                flood_and_replay_took_s=round(flood_end - t0, 1),
                replay_s=round(flood_s, 2),
                ratio_to_alone=round(flood_s / alone_s, 2),
                poses_equal=bool(np.array_equal(flooded, alone)),
                registration_peak_rss_mb=peak["rss_mb"],
                registration_max_rss_mb=cap,
                **{
                    role: counters(
                        session,
                        svc,
                        role,
                        ("streams_refused", "streams_refused_memory", "streams_evicted_memory", "streams_retired"),
                    )
                    for role in ("inference", "registration")
                },
            )
            time.sleep(max(0.0, args.settle_s - (time.perf_counter() - flood_end)))
            cpu0 = {r: cpu_s(p.pid) for r, p in svc.procs.items()}
            time.sleep(5.0)
            idle = {r: round(100 * (cpu_s(p.pid) - cpu0[r]) / 5.0, 1) for r, p in svc.procs.items()}
            after = workers(svc)
            emit(
                "settled",
                after_s=args.settle_s,
                workers=after,
                idle_cpu_pct=idle,
                rss_vs_baseline=({r: round(after[r]["rss_mb"] / base[r]["rss_mb"], 2) for r in base}),
                threads_vs_baseline=({r: round(after[r]["threads"] / base[r]["threads"], 2) for r in base}),
            )

        if "msgpack" in steps:
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
                        session.put(keys.camera(stream), hostile, congestion_control=BLOCK)
                    t = time.perf_counter()
                    c.step(frames[1])
                    return (time.perf_counter() - t) * 1000

            plain_ms = float(np.median([second_frame_ms(f"legit2p{i}", False) for i in range(3)]))
            after_ms = float(np.median([second_frame_ms(f"legit2h{i}", True) for i in range(3)]))
            emit(
                "msgpack",
                payload_mb=round(len(hostile) / 1e6, 1),
                frame_ms_alone=round(plain_ms, 1),
                frame_ms_after_hostile=round(after_ms, 1),
                delay_ms=round(after_ms - plain_ms, 1),
            )

        if "oversize" in steps:
            me = os.getpid()
            before = {**workers(svc), "router": proc_status(me)}
            session.put(keys.camera("legit3"), b"\x00" * (args.big_mb << 20), congestion_control=BLOCK)
            time.sleep(3.0)
            after = {**workers(svc), "router": proc_status(me)}
            emit(
                "oversize",
                put_mb=args.big_mb,
                rss_rise_mb={r: round(after[r]["rss_mb"] - before[r]["rss_mb"], 1) for r in after},
                note="router rise includes this process's own put buffer",
            )

        if "queries" in steps:
            with OccVOClient(ep, "legit0", timeout=60) as c:
                ix, iy = c.map_info().tiles[0]

                def tile_times(n=300):  # p99 is then the 3rd slowest, not one outlier
                    out = []
                    for _ in range(n):
                        t = time.perf_counter()
                        c.tile(ix, iy)
                        out.append((time.perf_counter() - t) * 1000)
                    return np.percentile(out, [50, 99]).round(2).tolist()

                quiet = tile_times()
                ctx = multiprocessing.get_context("spawn")  # the hostile client is a process of its own, as it would be
                hammer, counts = ctx.Event(), ctx.Array("i", 2)
                hostile_client = ctx.Process(target=wildcard_gets, args=(ep, 10, hammer, counts))
                hostile_client.start()
                while counts[0] + counts[1] < 10:  # its gets are being answered
                    time.sleep(0.05)
                loud = tile_times()
                hammer.set()
                hostile_client.join(60)
                answers = {"ok": counts[0], "busy": counts[1]}
            emit(
                "queries",
                tile_p50_p99_ms_alone=quiet,
                tile_p50_p99_ms_with_10_wildcard_gets=loud,
                wildcard_replies=answers,
                load_average=round(os.getloadavg()[0], 1),  # other jobs on the machine
                map=counters(session, svc, "map", ("queries_refused",)),
            )
        if "sequence" in steps:
            sequence_abuse(ep, frames, alone, alone_s)
        if "silent" in steps:
            silent_queryable(ep, "legit0")
        if "degenerate" in steps:
            degenerate_frames(ep, frames)
        if "log_flood" in steps:
            log_flood(ep, svc)
        if "grabber" in steps:
            grabber(ep, frames, alone_s, [[f"grab{i}" for i in range(50)]], "legit5", "plain default, one session")
        session.close()
    finally:
        svc.stop()
    if "heavy" in steps:
        heavy(args, frames, store, reg_config)
    if "config" in steps:
        bad_configs()
    if "disk_full" in steps and args.disk_full_dir:
        full_info = disk_full(args, frames, alone, reg_config)
        emit(
            "disk_full_map_vs_alone",
            same_tiles=full_info.tiles == alone_info.tiles,
            same_voxels=full_info.voxel_count == alone_info.voxel_count,
        )
        goal(
            "the map after the spell is the map of the run alone",
            full_info.tiles == alone_info.tiles and full_info.voxel_count == alone_info.voxel_count,
        )
    if "grabber" in steps:  # the ACL's identity rule: a client is the stream id's prefix (its user)
        svc = LocalService(
            quiet=True,
            common_args=["--client-identity", "user"],
            worker_args={
                "registration": ["--config", reg_config, *store, *reg_cap],
                "inference": ["--config", "deploy/inference_worker.json5"],
                "map": ["--config", "deploy/map_service.json5", *store],
            },
        ).start()
        try:
            solo_s, _ = run_replay(svc.endpoint, "viewer.solo", frames)
            users = [[f"camera{u}.s{i}" for i in range(16)] for u in range(1, 5)]
            grabber(svc.endpoint, frames, solo_s, users, "viewer.car", "client_identity user, 4 users x 16 streams")
        finally:
            svc.stop()
    return 0 if all(GOALS) else 1


if __name__ == "__main__":
    sys.exit(main())
