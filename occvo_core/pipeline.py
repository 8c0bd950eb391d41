"""Run the odometry over a scene source and write what users look at (KISS-ICP's pipeline.py in spirit)."""

from __future__ import annotations

import json
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from occvo_core.config import OccVOConfig
from occvo_core.errors import InvalidFrameError
from occvo_core.eval import ape_rmse, project_to_plane, rpe_errors, success
from occvo_core.io import plot_trajectory, write_ply
from occvo_core.odometry import OccVO
from occvo_core.time_fit import fit_time_offset
from occvo_core.trajectory import write_kitti, write_tum
from occvo_core.trajectory_stats import path_length, vertical_drift


class OdometryPipeline:
    def __init__(
        self,
        source,
        config: OccVOConfig | None = None,
        skip_bad_frames: bool = False,
        progress: bool = True,
        threads: int = 0,
    ):
        self.source = source
        self.odometry = OccVO(config, threads=threads)
        self.skip_bad_frames = skip_bad_frames
        self.progress = progress
        self.frame_ms: list[float] = []
        self.stage_ms: dict[str, list[float]] = {}
        self.skipped: list[str] = []
        self.stamp_of: dict[int, float] = {}  # frame index -> the data's stamp (s)

    def run(self, on_step=None) -> OdometryPipeline:
        """on_step(frame, result, odometry), when given, sees every registered frame (a live view logs it)."""
        self.odometry.reset()
        bar = tqdm(total=len(self.source), desc=f"OCC-VO {self.source.name}", unit="frame", disable=not self.progress)
        with bar:  # closed (its line ended) before an error or Ctrl-C is reported
            for i in range(len(self.source)):
                self._step(i, on_step)
                bar.update()
        return self

    def _step(self, i: int, on_step) -> None:
        try:
            frame = self.source[i]
            start = time.perf_counter()
            result = self.odometry.step(frame)
            self.stamp_of[frame.index] = float(frame.stamp)
        except InvalidFrameError as exc:
            if not self.skip_bad_frames:
                raise
            self.skipped.append(str(exc))
            return
        if result.status == "ok":  # the first frame only seeds the map
            self.frame_ms.append((time.perf_counter() - start) * 1e3)
            for stage, ms in result.timings_ms.items():
                self.stage_ms.setdefault(stage, []).append(ms)
        if on_step is not None:
            on_step(frame, result, self.odometry)

    def stamps(self) -> np.ndarray:
        """Stamps of the registered frames as the data gave them (index / rate only where a source has no clock)."""
        return np.array([self.stamp_of.get(i, i / self.source.rate_hz) for i in self.odometry.frame_indices], float)

    def gt_of_registered(self) -> np.ndarray | None:
        gt = self.source.gt_poses
        return None if gt is None else gt[self.odometry.frame_indices]

    def summary(self) -> dict:
        poses = self.odometry.poses
        gt = self.gt_of_registered()
        out: dict = {"scene": self.source.name, "frames": int(len(poses)), "skipped_frames": self.skipped}
        if gt is not None:
            scored = poses
            if getattr(self.source, "gt_on_map_plane", False):  # scored as the ground truth is given: on the plane
                out.update(ape_rmse_3d_m=ape_rmse(gt, poses), ape_on_map_plane=True)
                scored = project_to_plane(poses)
            rmse = ape_rmse(gt, scored)
            out.update(ape_rmse_m=rmse, success=success(rmse))
            if len(poses) >= 2:
                out["rpe_rmse_m"] = float(np.sqrt(np.mean(rpe_errors(gt, scored) ** 2)))
            if len(poses) >= 3:  # how much of the APE is timing between the frames and their poses
                fit = fit_time_offset(gt, scored, self.stamps())
                out.update(
                    ape_rmse_time_fitted_m=fit.ape_rmse_m,
                    time_offset_ms=fit.offset_ms,
                    time_fit_dropped_frames=fit.dropped_frames,
                )
        out.update(path_length_m=path_length(poses), **vertical_drift(poses))
        out["ms_per_frame_median"] = float(np.median(self.frame_ms)) if self.frame_ms else None
        out["ms_per_stage_median"] = {k: float(np.median(v)) for k, v in self.stage_ms.items()}
        # the map a user gets (map.npz, map.ply, the service's tiles): the voxel pfilter's persistent voxels; the
        # rest of the live voxels are candidates not yet seen often enough (map_voxels.npz holds them all)
        out["map_voxels"] = int(np.count_nonzero(self.odometry.map.persistent()))
        out["live_voxels"] = len(self.odometry.map)
        out["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
        return out

    def write(self, out_dir: str | Path, extra: dict | None = None) -> dict:
        """Every file is written under a temporary name in out_dir and renamed into place once all are written: an
        error or Ctrl-C leaves the folder as it was, never a half-written file."""
        out = Path(out_dir)
        out.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=out, prefix=".partial-") as tmp:
            summary = self._write_into(Path(tmp), extra)
            for f in sorted(Path(tmp).iterdir()):
                os.replace(f, out / f.name)
        return summary

    def _write_into(self, out: Path, extra: dict | None) -> dict:
        poses = self.odometry.poses
        write_kitti(out / "trajectory.kitti", poses)
        write_tum(out / "trajectory.tum", poses, self.stamps())
        points, labels = self.odometry.map_points()
        np.savez_compressed(out / "map.npz", points=points, labels=labels)
        np.savez_compressed(out / "map_voxels.npz", **self.odometry.map.arrays(len(poses)))
        write_ply(out / "map.ply", points, labels)
        gt = self.gt_of_registered()
        if gt is not None:  # what the estimate is scored against, on the same stamps: evo_ape tum groundtruth.tum ...
            write_kitti(out / "groundtruth.kitti", gt)
            write_tum(out / "groundtruth.tum", gt, self.stamps())
        plot_trajectory(out / "trajectory.png", poses, gt, title=self.source.name)
        summary = {**self.summary(), **(extra or {})}
        (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
        return summary
