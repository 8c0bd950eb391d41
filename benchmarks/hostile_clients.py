"""Hostile clients beside a legitimate replay, on loopback: the figures of issues 33 and 64's "done when".

    python benchmarks/hostile_clients.py [--modes logins,anonymous] [--steps ...] [--streams 2000 --flood-s 10
        --settle-s 60 --big-mb 512] [--registration-max-rss-mb MB] [--store-flood-s 180] [--disk-full-dir DIR]

Each pass runs against one deployment (_hostile_deploy.py): `logins`, `occvo serve`'s default (the router with logins
and access control, the workers as their logins, a client known by its login's prefix), every step; then
`anonymous` (`occvo serve --anonymous`: a plain router, a client known by the zid it declares), the steps that differ
there, their goals advisory (printed, not counted: the guards keyed on a self-declared id cannot hold). The victim is
the login `occvo serve` made for the user running it; an attacker comes without credentials, with its own login
(`mallory`) or with another user's (`bob`), never with the victim's. Router in this process, workers as processes
(occvo_services.local.LocalService, the deploy configs' limits). Steps:
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
  grabber_acl behind the shipped ACL (more camera users as it says), each worker and client its own login: 4 logins
             holding max_streams_per_client ids each beside a fifth login's replay: the same figures, streams served
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
  store_flood one session opening a fresh stream every --store-flood-period-s for --store-flood-s (default 180)
             against `occvo serve`'s worker configs: store growth against the client's quota, log bytes
  db_outage  `occvo serve`'s worker configs on a PostgreSQL store of the step's own, two replays; the database
             stopped for each of --outage-s (default 8; e.g. 8,60) once both have pose 10: every pose
             and the stored ones vs alone, the codes the clients got, resends, time
  members_acl two registration workers in placement members behind the shipped ACL, four replays as a camera
             login, the owner of the first stream killed (-9) at its pose 10: every pose vs alone, owners before
  lease_flood placement members on PostgreSQL: --lease-flood one-byte puts on new keys beside a replay: its poses
             vs alone, its time vs solo, the lease rows left
  share_flood placement members on PostgreSQL: one client puts a valid frame on each of --share-flood new stream ids
             (anonymous: occupancy frames straight to registration) beside a replay: its poses vs alone, its time vs
             solo, the most lease rows during the flood (at most the client's share, 16, and the replay's)
  no_credentials a session without credentials: refused by the router
  takeover   the victim's idle (retired, stored) stream: another user's login puts seq 0 to 5 of other frames on it:
             its stored trajectory and map before and after
  sybil      one login putting a frame every 2 s on 64 stream ids, each under another borrowed zid, beside the
             victim's replay: poses, stored trajectory, time vs a solo replay just before
  copied_id  the victim's zid copied (or leaked): another user's login puts other frames, seq 0-39 over and over, on
             the victim's stream under it while the victim replays: the same figures
  query_budget 10 attacker threads looping tile gets under the victim's copied zid (on the victim's stream and on
             its own) while the victim asks 200 tiles: the victim's gets refused busy
  fake_tokens placement members on PostgreSQL: the attacker's login declares 8 registration workers' tokens, then two
             replays: poses, time vs the same replays before, leases held by a fake worker
  secrets    `occvo serve` on PostgreSQL, the password in OCCVO_STORE_URL (`?password=`), the database stopped
             mid-drive: the password in ps, logs, output, events; written in --store: exit 2, one line
members_acl runs under the default's logins and under the shipped ACL (deploy/acl). $OCCVO_HOSTILE_LOGS: a folder for
the workers' logs. `alone` always runs (the baseline and the map the queries ask for); --steps picks the others. Prints one JSON line
per step and one per goal ({"goal": ..., "met": ...}); exits 1 if a goal is not met."""

from __future__ import annotations

import argparse
import functools
import multiprocessing
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
from _hostile_abuse import degenerate_frames, grabber, log_flood, msgpack_delay, sequence_abuse, silent_queryable
from _hostile_acl import grabber_acl, grabber_user
from _hostile_common import (
    BLOCK,
    DATA,
    GOALS,
    counters,
    cpu_s,
    emit,
    goal,
    proc_status,
    run_replay,
    wildcard_gets,
    worker_args,
    workers,
)
from _hostile_deploy import DEPLOY, Deployment, deploy
from _hostile_identity import copied_id, no_credentials, query_budget, sybil, takeover_idle
from _hostile_limits import bad_configs, disk_full, heavy
from _hostile_outage import db_outage, fake_tokens, lease_flood, members_acl, share_flood
from _hostile_secrets import secrets
from _hostile_store import store_flood

from occvo_core.datasets import OccVOReleaseScene
from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_services.client import OccVOClient, camera_frame_of
from occvo_services.runtime import WorkerConfig

STEPS = (
    "no_credentials,takeover,flood,msgpack,oversize,queries,sequence,silent,degenerate,log_flood,grabber,sybil,"
    "copied_id,query_budget,heavy,config,store_flood,disk_full,grabber_acl,db_outage,members_acl,lease_flood,"
    "share_flood,fake_tokens,secrets"
).split(",")
# where the anonymous mode differs: what rests on a client's identity, and the access control's refusals
ANONYMOUS_STEPS = {
    "no_credentials", "takeover", "sequence", "silent", "grabber", "sybil", "copied_id", "query_budget", "store_flood",
    "lease_flood", "share_flood", "fake_tokens",
}  # fmt: skip


def attempt(step, *args, **kw) -> None:
    """A step that raises is one failed goal naming the error, and the run goes on with the next step."""
    try:
        step(*args, **kw)
    except Exception as exc:  # noqa: BLE001 - reported as the step's result
        goal(f"{step.__name__} ran to its end", False, error=f"{type(exc).__name__}: {str(exc)[:300]}")


def main() -> int:
    p = argparse.ArgumentParser()
    p.add_argument("--streams", type=int, default=2000)
    p.add_argument("--flood-s", type=float, default=10.0)
    p.add_argument("--settle-s", type=float, default=60.0)
    p.add_argument("--big-mb", type=int, default=512)
    p.add_argument("--frames", type=int, default=40)
    p.add_argument(
        "--steps",
        default=",".join(STEPS),
        help="steps after `alone`, comma separated",
    )
    p.add_argument("--disk-full-dir", help="step disk_full: a small filesystem for the store (e.g. a 64 MB tmpfs)")
    p.add_argument("--full-s", type=float, default=5.0, help="step disk_full: how long the filesystem stays full")
    p.add_argument("--heavy-max-rss-mb", type=int, default=1024, help="the registration worker's cap in step heavy")
    p.add_argument("--heavy-frames", type=int, default=5, help="full-grid frames on each of the 4 heavy streams")
    p.add_argument("--registration-max-rss-mb", type=int, help="the registration worker's cap instead of its config's")
    p.add_argument("--store-flood-s", type=float, default=180.0, help="step store_flood: how long fresh streams open")
    p.add_argument("--store-flood-period-s", type=float, default=0.5, help="step store_flood: a new stream this often")
    p.add_argument(
        "--outage-s", default="8", help="step db_outage: how long the database is stopped, seconds (a comma list: each)"
    )
    p.add_argument("--lease-flood", type=int, default=20000, help="step lease_flood: one-byte puts on new keys")
    p.add_argument("--share-flood", type=int, default=200, help="step share_flood: new streams, a valid frame each")
    p.add_argument(
        "--modes",
        default="logins,anonymous",
        help="deployments: logins (the default's, every step) and anonymous (`--anonymous`: the steps that differ "
        "there, their goals advisory)",
    )
    args = p.parse_args()
    steps = set(args.steps.split(","))
    for mode in args.modes.split(","):
        anonymous = mode == "anonymous"
        todo = steps & ANONYMOUS_STEPS if anonymous else steps
        if not todo:
            continue
        DEPLOY.append(Deployment(anonymous))
        emit("deployment", mode=mode, steps=sorted(todo), advisory=anonymous)
        run_pass(args, todo)
    return 0 if all(GOALS) else 1


def run_pass(args, steps: set[str]) -> None:
    reg_config = "deploy/registration_worker.json5"
    cap = args.registration_max_rss_mb or WorkerConfig.load(reg_config).max_rss_mb
    reg_cap = ["--max-rss-mb", str(cap)] if args.registration_max_rss_mb else []
    scene = OccVOReleaseScene(DATA)
    frames = [scene[i] for i in range(min(args.frames, len(scene)))]
    store = ["--store-path", str(Path(tempfile.mkdtemp()) / "occvo.sqlite")]  # idle streams' state goes there
    args_of = functools.partial(worker_args, reg_config, reg_cap)  # the workers' arguments with a store
    svc = deploy().service(quiet=True, worker_args=args_of(store)).start()
    try:
        ep = svc.endpoint
        alone_s, alone = run_replay(ep, "legit0", frames)
        with OccVOClient(ep, "legit0", timeout=60) as c:
            deadline = time.monotonic() + 60
            while (alone_info := c.map_info()).last_seq != len(frames) - 1 and time.monotonic() < deadline:
                time.sleep(0.2)
        if "no_credentials" in steps:
            attempt(no_credentials, ep)
        session, login = deploy().attacker(ep, "own")  # the flood's, and oversize's
        # the flood's baseline is the service at rest: the replay's stream retired (idle_stream_s), as the flood's will
        # be; takeover's victim stream is that idle one
        deadline = time.monotonic() + WorkerConfig.load(reg_config).idle_stream_s + 60
        idle = {"flood", "takeover"} & steps
        while idle and counters(session, svc, "registration", ("streams_retired",))["streams_retired"] < 1:
            assert time.monotonic() < deadline, "the replay's stream was not retired"
            time.sleep(1.0)
        base = workers(svc)
        emit("alone", mode=deploy().name, replay_s=round(alone_s, 2), poses=len(alone), workers=base)

        if "takeover" in steps:
            attempt(takeover_idle, ep, frames, alone)
        if "flood" in steps:
            peak = {"rss_mb": 0.0}
            stop = threading.Event()

            # encoded before the flood (voxel indices: 0.12 MB each), so that putting them takes --flood-s, not the
            # encoding's time (21.8 s for 2,000 when encoded one by one)
            names = [deploy().wire(f"flood{i}", login) for i in range(args.streams)]
            payloads = [encode(camera_frame_of(frames[0], n, 0, exact=False)) for n in names]

            def flood():
                start = time.perf_counter()
                for i, (name, small) in enumerate(zip(names, payloads)):
                    session.put(keys.camera(name), small, congestion_control=BLOCK)
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
                mode=deploy().name,
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
            attempt(msgpack_delay, ep, frames)
        if "oversize" in steps:
            me = os.getpid()
            before = {**workers(svc), "router": proc_status(me)}
            session.put(
                keys.camera(deploy().wire("legit3", login)), b"\x00" * (args.big_mb << 20), congestion_control=BLOCK
            )
            time.sleep(3.0)
            after = {**workers(svc), "router": proc_status(me)}
            emit(
                "oversize",
                mode=deploy().name,
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
                hammer, counts = ctx.Event(), ctx.Array("i", 3)
                own = deploy().config("own")  # the attacker's own login: its gets on occvo/** (or none: refused)
                hostile_client = ctx.Process(target=wildcard_gets, args=(ep, 10, hammer, counts, own))
                hostile_client.start()
                while counts[2] < 10:  # its gets are being answered (or refused by the access control)
                    time.sleep(0.05)
                loud = tile_times()
                hammer.set()
                hostile_client.join(60)
                answers = {"ok": counts[0], "busy": counts[1]}
            emit(
                "queries",
                mode=deploy().name,
                tile_p50_p99_ms_alone=quiet,
                tile_p50_p99_ms_with_10_wildcard_gets=loud,
                wildcard_replies=answers,
                wildcard_gets=counts[2],
                load_average=round(os.getloadavg()[0], 1),  # other jobs on the machine
                map=counters(session, svc, "map", ("queries_refused",)),
            )
        if "sequence" in steps:
            attempt(sequence_abuse, ep, frames, alone, alone_s)
        if "silent" in steps:
            attempt(silent_queryable, ep, "legit0")
        if "degenerate" in steps:
            attempt(degenerate_frames, ep, frames)
        if "log_flood" in steps:
            attempt(log_flood, ep, svc)
        if "grabber" in steps:
            attempt(grabber, ep, frames, alone_s, [[f"grab{i}" for i in range(50)]], "legit5", "one session, 50 ids")
        if "sybil" in steps:
            attempt(sybil, ep, frames, alone, alone_s)
        if "copied_id" in steps:
            attempt(copied_id, ep, frames, alone, alone_s)
        if "query_budget" in steps:
            attempt(query_budget, ep, frames)
        session.close()
    finally:
        svc.stop()
    if "heavy" in steps:
        attempt(heavy, args, frames, store, reg_config)
    if "config" in steps:
        attempt(bad_configs)
    if "store_flood" in steps:
        attempt(store_flood, args, frames)
    if "disk_full" in steps and args.disk_full_dir:
        try:
            full_info = disk_full(args, frames, alone, reg_config)
        except Exception as exc:  # noqa: BLE001 - reported as the step's result
            full_info = None
            goal("disk_full ran to its end", False, error=f"{type(exc).__name__}: {str(exc)[:300]}")
    if "disk_full" in steps and args.disk_full_dir and full_info is not None:
        emit(
            "disk_full_map_vs_alone",
            same_tiles=full_info.tiles == alone_info.tiles,
            same_voxels=full_info.voxel_count == alone_info.voxel_count,
        )
        goal(
            "the map after the spell is the map of the run alone",
            full_info.tiles == alone_info.tiles and full_info.voxel_count == alone_info.voxel_count,
        )
    if "grabber" in steps and deploy().anonymous:  # the ACL's identity rule without its logins
        attempt(grabber_user, frames, args_of(store))
    if "grabber_acl" in steps:
        attempt(grabber_acl, frames, args_of, reg_config)
    for outage_s in [float(x) for x in args.outage_s.split(",")] if "db_outage" in steps else []:
        attempt(db_outage, outage_s, frames, alone)
    if "members_acl" in steps:
        attempt(members_acl, frames, alone, shipped=False)
        attempt(members_acl, frames, alone, shipped=True)
    if "lease_flood" in steps:
        attempt(lease_flood, args, frames, alone_s, alone)
    if "share_flood" in steps:
        attempt(share_flood, args, frames, alone_s, alone)
    if "fake_tokens" in steps:
        attempt(fake_tokens, frames, alone)
    if "secrets" in steps:
        attempt(secrets, frames)


if __name__ == "__main__":
    sys.exit(main())
