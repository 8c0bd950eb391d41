"""Hostile-client steps of heavy frames, bad configurations and a full disk (benchmarks/hostile_clients.py)."""

from __future__ import annotations

import json
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
from _hostile_common import (
    BLOCK,
    counters,
    emit,
    goal,
    proc_status,
    run_replay,
)
from _hostile_deploy import deploy

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_services.client import OccVOClient
from occvo_services.commands.replay import replay


def heavy(args, frames, store: list[str], reg_config: str) -> None:
    """Heavy frames on 4 streams beside a replay, the registration worker capped at --heavy-max-rss-mb: a frame of
    3.5 M copies of one voxel (refused: more voxels than the grid's cells) then full-grid frames (640,000 voxels)."""
    from occvo_core.grid import OCC3D_GRID
    from occvo_schemas.models import CameraFrame, SparseOccupancy

    cap = args.heavy_max_rss_mb
    svc = (
        deploy()
        .service(
            quiet=True,
            worker_args={
                "registration": ["--config", reg_config, *store, "--max-rss-mb", str(cap)],
                "inference": ["--config", "deploy/inference_worker.json5"],
                "map": ["--config", "deploy/map_service.json5", *store],
            },
        )
        .start()
    )
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
                try:
                    peak["rss_mb"] = max(peak["rss_mb"], proc_status(svc.procs["registration"].pid)["rss_mb"])
                except (KeyError, OSError):  # the worker gone (the step ended early)
                    return

        def heavy_client(i):
            session, login = deploy().attacker(ep, "own")
            stream = deploy().wire(f"heavy{i}", login)
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
        try:
            took, poses, lost = *run_replay(ep, "heavylegit", frames), None
        except AssertionError as exc:  # frames of the replay refused for good: said below, the step goes on
            took, poses, lost = float("nan"), np.zeros((0, 4, 4)), str(exc)[:400]
        for t in clients:
            t.join()
        time.sleep(5.0)  # the heavy frames queued are registered
        stop.set()
        session = svc.router
        refused = counters(
            session, svc, "registration", ("frames_refused_memory", "streams_refused_memory", "frames_out", "errors")
        )
        refused_inf = counters(session, svc, "inference", ("errors",))
        emit(
            "heavy",
            mode=deploy().name,
            registration_max_rss_mb=cap,
            registration_peak_rss_mb=peak["rss_mb"],
            replay_s=round(took, 2),
            solo_s=round(solo_s, 2),
            ratio_to_solo=round(took / solo_s, 2),
            poses=len(poses),
            replay_lost=lost,
            registration=refused,
            inference=refused_inf,
        )
        goal(
            "heavy-frame streams keep the registration worker's RSS under max_rss_mb",
            peak["rss_mb"] < cap,
            peak_rss_mb=peak["rss_mb"],
            cap=cap,
        )
        goal("beside heavy-frame streams the replay gets all its poses", lost is None, refused=lost)
    finally:
        svc.stop()


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
    svc = (
        deploy()
        .service(
            quiet=True,
            worker_args={
                "registration": ["--config", reg_config, *store],
                "inference": ["--config", "deploy/inference_worker.json5"],
                "map": ["--config", "deploy/map_service.json5", *store],
            },
        )
        .start()
    )
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
