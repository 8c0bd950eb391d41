"""long_drive.py's report of a drive: memory over the laps, the trajectory's APE, and the start area's map at the end of
lap 1 against the last lap's."""

from __future__ import annotations

import statistics
import time

import numpy as np
import psutil
from _common import vm_hwm_mb
from _drive_truth import cell_keys, seen_cells, true_start_map
from scipy.spatial import cKDTree

from occvo_core.eval import ape_rmse
from occvo_core.map_metrics import map_metrics
from occvo_core.sim import SyntheticScene


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
