"""Is the real scenes' along-track error the odometry's, or a time offset between the release's occupancy and its
ground-truth poses? Each scene is run four ways, and only an offset in the data changes sign the way it does:

    python benchmarks/time_offset.py [--scenes scene-0101 scene-0268] [--config CONFIG.json5]

  forward      the frames as released;
  reversed     the frames in reverse order (the car drives backwards in time);
  turned       every frame turned 180 degrees about z (the same drive with the sensors facing back);
  turned+rev   both.

For each run: APE RMSE, and the time shift dt (-300..300 ms) of the ground truth that fits the trajectory best. With
  d = a data offset (frames taken d after their poses): dt = +d forward and turned, -d reversed and turned+rev;
  e = a lead fixed in the ego frame (e.g. which voxel of a block is a GICP source): +e, -e, -e, +e;
  l = a lead along the direction of travel (e.g. a scale): +l in all four;
so d, e and l are read off the four shifts by least squares (each is a sum of the four with signs, over 4); the
fourth such sum, signs +, +, -, -, is what the three leave unexplained (the residual; 0 if they explain it all).
Last, the APE that an exact odometry would score against these poses if the frames lie d after them, and its
path length over the truth's.
Prints a table and one JSON line.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from _common import RUNS, benchmark_main, four_ways, shifted

from occvo_core import OccVO, OccVOConfig
from occvo_core.eval import ape_rmse
from occvo_core.trajectory_stats import path_length

FRAME_MS = 500.0  # nuScenes keyframes, 2 Hz
SHIFTS = np.arange(-0.6, 0.6001, 0.01)  # keyframes: -300..300 ms


def best_shift_ms(gt: np.ndarray, est: np.ndarray) -> tuple[float, float]:
    apes = [ape_rmse(shifted(gt, s), est) for s in SHIFTS]
    best = int(np.argmin(apes))
    return float(SHIFTS[best] * FRAME_MS), float(apes[best])


def run(frames: list, config: OccVOConfig) -> np.ndarray:
    vo = OccVO(config)
    for frame in frames:
        vo.step(frame)
    return vo.poses


def measure(root: Path, name: str, config: OccVOConfig) -> dict:
    inputs = four_ways(root, name)
    forward = inputs["forward"][1]
    out = {"runs": {}}
    for run_name, (seq, poses) in inputs.items():
        poses = np.linalg.inv(poses[0]) @ poses
        est = run(seq, config)
        shift, ape_shifted = best_shift_ms(poses, est)
        out["runs"][run_name] = {
            "ape_rmse_m": ape_rmse(poses, est),
            "best_shift_ms": shift,
            "ape_at_best_shift_m": ape_shifted,
        }
    signs = np.array([RUNS[r] for r in inputs], np.float64)
    shifts = np.array([out["runs"][r]["best_shift_ms"] for r in inputs])
    d, e, lead, residual = signs.T @ shifts / 4.0  # the sign columns are orthogonal
    exact = shifted(forward, d / FRAME_MS)  # an exact odometry of frames d after their poses
    out.update(
        data_offset_ms=float(d),
        ego_lead_ms=float(e),
        travel_lead_ms=float(lead),
        residual_ms=float(residual),
        exact_odometry_ape_m=ape_rmse(forward, exact),
        # the offset alone makes a path longer or shorter when the car speeds up or slows down
        exact_odometry_path_ratio=path_length(exact) / path_length(forward),
    )
    return out


if __name__ == "__main__":
    sys.exit(benchmark_main(sys.argv[1:], __doc__, measure))
