"""Long loop drive through the service with flat memory: a synthetic drive lapping a block circuit
(SyntheticScene route="loop"), replayed losslessly (window 4) through router + inference + registration + map
workers as separate processes, the registration worker's RSS sampled every second.

    python benchmarks/long_drive.py [--frames 3600] [--seed 0] [--blocks 4x4] [--radius 150]
    python benchmarks/long_drive.py --frames 300 --blocks 2x2          # a short run for development

Reports: frames, wall time; registration-worker RSS median / peak of the first half vs the last half of the drive
and their ratio (goal: last-half peak <= 1.1 x first-half peak), VmHWM at the half and at the end; map voxels
served; APE RMSE of the whole trajectory against the scene's gt_poses (occvo_core.eval); and the revisited start:
the map tiles around the start (20 m tiles, [-20, 20) m in x and y of the odometry frame, which is the first
pose's) queried at the last frame of lap 1 before the ego comes back near its start, against the same query at
the same point of the last full lap (after every revisit): precision and completion (occvo_core.map_metrics,
0.4 m, static classes) in the cells lap 1's cameras saw (goal precision >= 0.9: where lap 1 built a map to match)
and over the whole start area, and of the last lap's start voxels farther than 0.4 m from lap 1's, the share on
the true static map (structure lap 1 did not see, against misplaced voxels). Eviction (--radius with
a durable store) is used when the registration worker has --store-path; otherwise the run says "eviction: off".
Prints a table, then one JSON line.
"""

from __future__ import annotations

import argparse
import json
import pickle
import statistics
import subprocess
import sys
import tempfile
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import psutil
from scipy.spatial import cKDTree

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
warnings.filterwarnings("ignore", category=RuntimeWarning)

from occvo_core.eval import ape_rmse  # noqa: E402
from occvo_core.grid import OCC3D_GRID  # noqa: E402
from occvo_core.map_metrics import map_metrics  # noqa: E402
from occvo_core.sim import SyntheticScene  # noqa: E402
from occvo_services.client import OccVOClient, ServiceError  # noqa: E402
from occvo_services.commands.replay import replay  # noqa: E402
from occvo_services.local import REPO, LocalService  # noqa: E402

START_TILES = dict(ix_min=-1, ix_max=0, iy_min=-1, iy_max=0)  # 20 m tiles: [-20, 20) m around the first pose


def worker_has_store() -> bool:
    out = subprocess.run(
        [sys.executable, "-m", "occvo_services.registration_worker", "--help"],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=60,
    )
    return "--store-path" in out.stdout and "--working-radius-m" in out.stdout


def vm_hwm_mb(pid: int) -> float:
    """Peak resident set of a process so far (Linux /proc VmHWM), MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def snapshot_frames(scene: SyntheticScene, away_m: float = 80.0) -> tuple[list[int], float]:
    """For each full lap, its last frame at which the ego is still at least `away_m` (or 80 % of the lap's
    farthest distance) from its start, i.e. just before it comes back there; and that distance in lap 1."""
    if len(scene.lap_starts) < 3:
        raise SystemExit(
            f"the drive must do at least 2 full laps, this one does {len(scene.lap_starts) - 1} "
            f"(laps start at frames {scene.lap_starts.tolist()}): more --frames or smaller --blocks"
        )
    xy = scene.gt_poses[:, :2, 3]
    d = np.linalg.norm(xy - xy[0], axis=1)

    def last_far(a: int, b: int) -> int:
        thr = min(away_m, 0.8 * d[a:b].max())
        return a + int(np.nonzero(d[a:b] >= thr)[0][-1])

    ks = [last_far(a, b) for a, b in zip(scene.lap_starts[:-1], scene.lap_starts[1:])]
    return ks, float(d[ks[0]])


class Budget(Exception):
    """The time budget ran out: the drive stops at the frame in hand."""


def true_start_map(scene: SyntheticScene, near_m: float = 80.0) -> tuple[np.ndarray, np.ndarray]:
    """The true static voxels of the start area seen from any frame within `near_m` of the start, in the
    odometry frame (the first pose's), cut to the START_TILES box."""
    poses = scene.gt_poses
    d = np.linalg.norm(poses[:, :2, 3] - poses[0, :2, 3], axis=1)
    pts, labels = scene.static_map(frames=np.nonzero(d <= near_m)[0])
    inv = np.linalg.inv(poses[0])
    pts = pts @ inv[:3, :3].T + inv[:3, 3]
    keep = np.all((pts[:, :2] >= -20.0) & (pts[:, :2] < 20.0), axis=1)
    return pts[keep], labels[keep]


def seen_cells(scene: SyntheticScene, poses: np.ndarray, frames, voxel: float = 0.4) -> np.ndarray:
    """Keys of the 0.4 m cells of the start box (odometry frame) that some camera saw in `frames`, free cells
    included, placed by the odometry's own poses: where a map built from those frames could have voxels."""
    keys = []
    for i in frames:
        pts = OCC3D_GRID.centres_of(np.argwhere(scene.camera_mask(int(i))))
        pts = pts @ poses[i][:3, :3].T + poses[i][:3, 3]
        keys.append(cell_keys(pts[np.all((pts[:, :2] >= -20.4) & (pts[:, :2] < 20.4), axis=1)], voxel))
    return np.unique(np.concatenate(keys)) if keys else np.zeros(0, np.int64)


def cell_keys(points: np.ndarray, voxel: float = 0.4) -> np.ndarray:
    c = np.floor(np.asarray(points) / voxel).astype(np.int64) + 1024  # the start box is +-60 cells, heights +-20
    return (c[:, 0] << 22) | (c[:, 1] << 11) | c[:, 2]


class RssSampler(threading.Thread):
    """RSS of one process every `period` s, with how many poses had come back by then."""

    def __init__(self, pid: int, done, period: float = 1.0):
        super().__init__(daemon=True)
        self.proc, self.done, self.period = psutil.Process(pid), done, period
        self.samples: list[tuple[float, int, float]] = []  # (t, frames done, rss MB)
        self.halt = threading.Event()

    def run(self) -> None:
        t0 = time.perf_counter()
        while not self.halt.is_set():
            try:
                rss = self.proc.memory_info().rss / 2**20
            except psutil.Error:
                return
            self.samples.append((time.perf_counter() - t0, self.done(), rss))
            self.halt.wait(self.period)


def start_map(client: OccVOClient, seq: int, timeout: float = 120.0) -> tuple[np.ndarray, np.ndarray]:
    """The service's map around the start once frame `seq` is registered and its map update applied."""
    client.wait_pose(seq, timeout)
    deadline = time.monotonic() + 30.0
    while time.monotonic() < deadline:
        try:
            info = client.map_info()
            if info.last_seq is not None and info.last_seq >= seq:
                break
        except ServiceError:
            pass
        time.sleep(0.05)
    try:
        tiles = client.region(**START_TILES)
    except ServiceError:
        tiles = []
    if not tiles:
        return np.zeros((0, 3)), np.zeros(0, np.uint8)
    return (np.concatenate([t.points.to_numpy() for t in tiles]), np.concatenate([t.labels.to_numpy() for t in tiles]))


def run(args, scene: SyntheticScene) -> dict:
    """Replay the drive through the service; returns the raw measurements (pickled by main before analysis)."""
    laps, away = snapshot_frames(scene)
    n = len(scene)
    eviction = (not args.no_store) and worker_has_store()
    with tempfile.TemporaryDirectory(prefix="occvo-long-") as tmp:
        log_dir = Path(args.log_dir or tmp)
        log_dir.mkdir(parents=True, exist_ok=True)
        reg_args = (
            ["--store-path", str(Path(tmp) / "occvo.db"), "--working-radius-m", str(args.radius)] if eviction else []
        )
        if args.after_pose_nice is not None:
            reg_args += ["--after-pose-nice", str(args.after_pose_nice)]
        svc = LocalService(
            worker_args={"registration": reg_args}, common_args=["--log-level", "WARNING"], log_dir=log_dir
        )
        svc.start()
        try:
            with OccVOClient(svc.endpoint, stream="loop") as client:
                client.wait_for_workers(timeout=60)
                pid = svc.procs["registration"].pid
                sampler = RssSampler(pid, lambda: len(client.poses))
                snaps, marks = {}, {}
                t_run = time.perf_counter()

                def progress(i: int, total: int) -> None:
                    if i in laps:
                        snaps[laps.index(i) + 1] = (i, *start_map(client, i, args.timeout))
                    if args.budget_s and time.perf_counter() - t_run > args.budget_s:
                        raise Budget(i)
                    if i == total // 2:
                        client.wait_pose(i, args.timeout)
                        marks["hwm_half"] = vm_hwm_mb(pid)
                        marks["voxels_half"] = client.map_info().voxel_count
                    if i % 300 == 0:
                        print(
                            f"  frame {i}/{total}  {time.perf_counter() - t_run:.0f} s  registration rss "
                            f"{psutil.Process(pid).memory_info().rss / 2**20:.0f} MB  hwm {vm_hwm_mb(pid):.0f} MB",
                            flush=True,
                        )

                sampler.start()
                try:
                    out = replay(client, scene, window=args.window, timeout=args.timeout, progress=progress)
                except Budget as stop:  # keep what was sent: wait for it, then report on those frames
                    sent = int(stop.args[0]) + 1
                    client.wait_pose(sent - 1, args.timeout)
                    poses = dict(client.poses)
                    out = {
                        "frames": sent,
                        "poses": len(poses),
                        "errors": len(client.errors),
                        "seconds": time.perf_counter() - t_run,
                        "trajectory": np.array([poses[q].matrix() for q in sorted(poses)]),
                        "budget_stop": True,
                    }
                    out["fps"] = out["poses"] / out["seconds"]
                    print(
                        f"  time budget of {args.budget_s:g} s reached: the drive stops after {sent} frames", flush=True
                    )
                finally:
                    sampler.halt.set()
                    sampler.join()
                hwm_end = vm_hwm_mb(pid)
                info_end = client.map_info()
                reg = {h.role: h for h in client.stats()}.get("registration")
                n_done = out["frames"]
                snaps["end"] = (n_done - 1, *start_map(client, n_done - 1, args.timeout))
        finally:
            codes = svc.stop()
        if out["poses"] != out["frames"]:
            for p in sorted(log_dir.glob("*.log")):
                print(p.name, p.read_text()[-2000:], file=sys.stderr)
    return {
        "n": n_done,
        "n_planned": n,
        "eviction": eviction,
        "snapshot_frames": laps,
        "away_m": away,
        "out": {k: v for k, v in out.items() if k != "pose_msgs"},
        "samples": sampler.samples,
        "snaps": snaps,
        "marks": marks,
        "hwm_end": hwm_end,
        "voxels_end": info_end.voxel_count,
        "tiles_end": info_end.tile_count,
        "registration_counters": dict(reg.counters) if reg else {},
        "registration_stages_ms": {k: v.mean_ms for k, v in reg.stages.items()} if reg else {},
        "exit_codes": codes,
        "bench_rss_mb": psutil.Process().memory_info().rss / 2**20,
    }


def analyse(raw: dict, scene: SyntheticScene, args, t_build: float) -> dict:
    n, out, marks = raw["n"], raw["out"], raw["marks"]
    eviction = raw["eviction"]
    laps_done = sorted(k for k in raw["snaps"] if k != "end")
    snaps, frame_of = {}, {}
    for name, k in (
        ("first", laps_done[0] if laps_done else None),
        ("second", laps_done[1] if len(laps_done) > 2 else None),
        ("last", laps_done[-1] if len(laps_done) > 1 else None),
        ("end", "end"),
    ):
        if k is not None and k in raw["snaps"]:
            frame_of[name], *snaps[name] = raw["snaps"][k]
    k_first, k_last = frame_of.get("first"), frame_of.get("last")
    half = n / 2
    first = [r for _, f, r in raw["samples"] if f < half]
    last = [r for _, f, r in raw["samples"] if f >= half]
    traj = out["trajectory"]
    ape = ape_rmse(scene.gt_poses[: len(traj)], traj) if len(traj) == n and n > 2 else float("nan")
    empty = (np.zeros((0, 3)), np.zeros(0, np.uint8))
    rev = map_metrics(*snaps.get("last", empty), *snaps.get("first", empty))  # NaN / 0 when a lap is missing
    rev_end = map_metrics(*snaps.get("end", empty), *snaps.get("first", empty))
    rev2 = map_metrics(*snaps["last"], *snaps["second"]) if "second" in snaps and "last" in snaps else None
    truth = true_start_map(scene)
    vs_truth = {
        k: round(map_metrics(*snaps[k], *truth).precision, 4) for k in ("first", "second", "last", "end") if k in snaps
    }
    # what the revisit added beyond lap 1's map: structure lap 1 did not see (on the true map), or misplaced
    new_on_truth = float("nan")
    if "last" in snaps and "first" in snaps and len(snaps["first"][0]) and len(snaps["last"][0]):
        beyond = cKDTree(snaps["first"][0]).query(snaps["last"][0])[0] > 0.4
        if beyond.any():
            new_on_truth = float(np.mean(cKDTree(truth[0]).query(snaps["last"][0][beyond])[0] <= 0.4))
    # the same, only where lap 1's cameras looked: a later lap's voxels elsewhere have nothing to match
    rev_seen = rev_seen_shifted = seen_share = None
    if "last" in snaps and "first" in snaps and len(traj) > k_first:
        d = np.linalg.norm(scene.gt_poses[: k_first + 1, :2, 3] - scene.gt_poses[0, :2, 3], axis=1)
        seen = seen_cells(scene, np.asarray(traj), np.nonzero(d <= 80.0)[0])

        def where_seen(points, labels):
            inside = np.isin(cell_keys(points), seen)
            return map_metrics(points[inside], labels[inside], *snaps["first"]), inside

        rev_seen, inside = where_seen(*snaps["last"])
        seen_share = float(inside.mean()) if len(inside) else float("nan")
        rev_seen_shifted, _ = where_seen(snaps["last"][0] + [0.4, 0.0, 0.0], snaps["last"][1])  # a map one voxel off
    stages = raw["registration_stages_ms"]
    res = {
        "frames": n,
        "frames_planned": raw["n_planned"],
        "budget_stop": bool(out.get("budget_stop")),
        "poses": out["poses"],
        "errors": out["errors"],
        "seed": args.seed,
        "blocks": args.blocks,
        "lap_m": round(scene.lap_length_m, 1),
        "laps": len(scene.lap_starts) - 1,
        "eviction": eviction,
        "radius_m": args.radius if eviction else None,
        "wall_s": round(out["seconds"], 1),
        "fps": round(out["fps"], 3),
        "scene_build_s": round(t_build, 1),
        "rss_first_median_mb": round(statistics.median(first), 1) if first else None,
        "rss_first_peak_mb": round(max(first), 1) if first else None,
        "rss_last_median_mb": round(statistics.median(last), 1) if last else None,
        "rss_last_peak_mb": round(max(last), 1) if last else None,
        "rss_peak_ratio": round(max(last) / max(first), 3) if first and last else None,
        "vmhwm_half_mb": round(marks.get("hwm_half", float("nan")), 1),
        "vmhwm_end_mb": round(raw["hwm_end"], 1),
        "rss_samples": len(raw["samples"]),
        "map_voxels_half": marks.get("voxels_half"),
        "map_voxels_end": raw["voxels_end"],
        "map_tiles_end": raw["tiles_end"],
        "registration_counters": raw["registration_counters"],
        "registration_stage_mean_ms": {k: round(v, 1) for k, v in stages.items()},
        "ape_rmse_m": round(ape, 3),
        "start_snapshot_frames": {k: int(v) for k, v in frame_of.items()},
        "full_laps_done": len(laps_done),
        "start_snapshot_away_m": round(raw["away_m"], 1),
        "start_voxels": {k: int(len(v[0])) for k, v in snaps.items()},
        "revisit_precision": round(rev.precision, 4),
        "revisit_completion": round(rev.completion, 4),
        "end_precision": round(rev_end.precision, 4),
        "end_completion": round(rev_end.completion, 4),
        "revisit_beyond_lap1_on_truth": round(new_on_truth, 4),
        "revisit_precision_where_lap1_looked": round(rev_seen.precision, 4) if rev_seen else None,
        "revisit_share_where_lap1_looked": round(seen_share, 4) if seen_share is not None else None,
        "revisit_precision_where_lap1_looked_shifted_0_4m": round(rev_seen_shifted.precision, 4)
        if rev_seen_shifted
        else None,
        "lap2_vs_last_precision": round(rev2.precision, 4) if rev2 else None,
        "lap2_vs_last_completion": round(rev2.completion, 4) if rev2 else None,
        "start_precision_vs_truth": vs_truth,
        "start_truth_voxels": int(len(truth[0])),
        "bench_process_rss_mb": round(raw["bench_rss_mb"], 1),
        "worker_exit_codes": raw["exit_codes"],
    }
    edges = list(scene.lap_starts) + [n]
    res["rss_peak_by_lap_mb"] = [
        round(max(r for _, f, r in raw["samples"] if a <= f < b), 1)
        for a, b in zip(edges[:-1], edges[1:])
        if a < n and any(a <= f < b for _, f, _ in raw["samples"])
    ]
    res["flat_memory"] = bool(res["rss_peak_ratio"] is not None and res["rss_peak_ratio"] <= 1.1)
    # the goal is judged where lap 1's cameras looked: there lap 1 built a map to match; elsewhere the last lap's
    # voxels are structure lap 1 never saw (its map of the start is taken before it came back), with nothing to match
    res["revisit_ok"] = bool(rev_seen is not None and rev_seen.precision >= 0.9)
    sv = res["start_voxels"]
    rows = [
        (
            "frames (poses / errors)",
            f"{n} of {raw['n_planned']} ({out['poses']} / {out['errors']})"
            + (" - stopped by the time budget" if out.get("budget_stop") else ""),
        ),
        ("loop", f"{args.blocks} blocks, {scene.lap_length_m:.0f} m a lap, {len(laps_done)} full laps driven"),
        (
            "eviction",
            f"on, working radius {args.radius:g} m, SQLite store"
            if eviction
            else "off (no store in the registration worker)",
        ),
        ("wall time", f"{out['seconds']:.0f} s ({out['fps']:.2f} frames/s)"),
        (
            "registration mean ms: registration / map_update / stage_total",
            " / ".join(f"{stages.get(k, float('nan')):.0f}" for k in ("registration", "map_update", "stage_total")),
        ),
        (
            "registration RSS median, first / last half",
            f"{res['rss_first_median_mb']} / {res['rss_last_median_mb']} MB",
        ),
        ("registration RSS peak, first / last half", f"{res['rss_first_peak_mb']} / {res['rss_last_peak_mb']} MB"),
        ("peak ratio last / first (goal <= 1.10)", f"{res['rss_peak_ratio']}"),
        ("registration RSS peak by lap", " ".join(f"{v:.0f}" for v in res["rss_peak_by_lap_mb"]) + " MB"),
        ("VmHWM at half / end", f"{res['vmhwm_half_mb']} / {res['vmhwm_end_mb']} MB"),
        ("map voxels served at half / end", f"{res['map_voxels_half']} / {res['map_voxels_end']}"),
        ("APE RMSE (whole drive)", f"{ape:.3f} m"),
        (
            "start map last lap vs lap 1 where lap 1's cameras looked: precision (goal >= 0.9)",
            f"{rev_seen.precision:.4f} ({seen_share:.4f} of the last lap's voxels; the last lap moved 0.4 m in x: "
            f"{rev_seen_shifted.precision:.4f})"
            if rev_seen
            else "n/a",
        ),
        (
            "the same over the whole start area",
            f"{rev.precision:.4f} (completion {rev.completion:.4f}, "
            f"{sv.get('last')} vs {sv.get('first')} voxels, frames {k_last} vs {k_first})",
        ),
        ("last lap's start voxels beyond 0.4 m of lap 1's: share on the true map", f"{new_on_truth:.4f}"),
        (
            "start map end of drive vs lap 1: precision",
            f"{rev_end.precision:.4f} (completion {rev_end.completion:.4f})",
        ),
        (
            "start map last lap vs lap 2: precision",
            f"{rev2.precision:.4f} (completion {rev2.completion:.4f})" if rev2 else "n/a (< 3 laps)",
        ),
        ("start map precision vs the true static map", ", ".join(f"{k} {v:.4f}" for k, v in vs_truth.items())),
    ]
    w = max(len(r[0]) for r in rows)
    for k, v in rows:
        print(f"{k:<{w}}  {v}")
    return res


def generate_only(scene: SyntheticScene, t_build: float) -> dict:
    """Render every frame of the drive in this process (no service): ms a frame and this process's RSS over the
    first vs the last half of the drive."""
    proc = psutil.Process()
    n, rss, ms = len(scene), [], []
    for i in range(n):
        t = time.perf_counter()
        scene[i]
        ms.append((time.perf_counter() - t) * 1000.0)
        if i % 10 == 0:
            rss.append((i, proc.memory_info().rss / 2**20))
        if i % 300 == 299:
            print(
                f"  frame {i + 1}/{n}  median {statistics.median(ms[-300:]):.0f} ms a frame  rss {rss[-1][1]:.0f} MB  "
                f"hwm {vm_hwm_mb(proc.pid):.0f} MB  cached {len(scene._frames)}",
                flush=True,
            )
    first = [r for i, r in rss if i < n / 2]
    last = [r for i, r in rss if i >= n / 2]
    res = {
        "mode": "generate",
        "frames": n,
        "scene_build_s": round(t_build, 1),
        "ms_per_frame_median": round(statistics.median(ms), 1),
        "ms_per_frame_mean": round(statistics.fmean(ms), 1),
        "rss_first_peak_mb": round(max(first), 1),
        "rss_last_peak_mb": round(max(last), 1),
        "rss_peak_ratio": round(max(last) / max(first), 3),
        "vmhwm_mb": round(vm_hwm_mb(proc.pid), 1),
        "frames_cached": len(scene._frames),
        "town_mb": round(scene.town.nbytes() / 1e6, 1),
        "tracks": len(scene.tracks),
    }
    print(
        f"generated {n} frames: median {res['ms_per_frame_median']} ms a frame (build {t_build:.1f} s); RSS peak first / last "
        f"half {res['rss_first_peak_mb']} / {res['rss_last_peak_mb']} MB (ratio {res['rss_peak_ratio']}), VmHWM {res['vmhwm_mb']} MB"
    )
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=3600)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--blocks", default="4x4", help="loop around NXxNY city blocks (4x4: ~1.1 km a lap)")
    ap.add_argument("--radius", type=float, default=120.0, help="registration working radius, m (with a store)")
    ap.add_argument("--window", type=int, default=4)
    ap.add_argument(
        "--after-pose-nice",
        type=int,
        help="niceness of the registration worker's work after a pose "
        "(default: the worker's, 10; 0: the lanes', faster for one stream replayed as fast as it goes)",
    )
    ap.add_argument("--no-store", action="store_true", help="run without the durable store and eviction")
    ap.add_argument("--timeout", type=float, default=300.0, help="s without a pose before the replay gives up")
    ap.add_argument("--log-dir", help="keep the workers' logs here (default: a temporary folder)")
    ap.add_argument("--budget-s", type=float, default=0.0, help="stop the drive after this many seconds (0: none)")
    ap.add_argument("--raw", help="pickle the raw measurements here (default: a temporary file)")
    ap.add_argument("--analyse", metavar="RAW", help="only analyse a pickle written by an earlier run (same flags)")
    ap.add_argument(
        "--generate-only", action="store_true", help="only time the scene's frames and this process's memory"
    )
    args = ap.parse_args()
    blocks = tuple(int(v) for v in args.blocks.lower().split("x"))
    t_build = time.perf_counter()
    scene = SyntheticScene(seed=args.seed, frames=args.frames, route="loop", loop_blocks=blocks)
    t_build = time.perf_counter() - t_build
    if args.generate_only:
        print(json.dumps(generate_only(scene, t_build)))
        return 0
    if args.analyse:
        raw = pickle.loads(Path(args.analyse).read_bytes())
    else:
        raw = run(args, scene)
        path = Path(args.raw or tempfile.mkstemp(prefix="occvo-long-", suffix=".pkl")[1])
        path.write_bytes(pickle.dumps(raw))
        print(f"raw measurements: {path}")
    res = analyse(raw, scene, args, t_build)
    print(json.dumps(res))
    return 0 if res["poses"] == res["frames"] else 1


if __name__ == "__main__":
    sys.exit(main())
