"""The benchmarks run (a benchmark that rots unseen once crashed on a changed signature): short runs of those that
finish in seconds, checked for what they report."""

import importlib.util
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
# open3d's GICP is these two benchmarks' cross-check: it comes with the bench extra (pip install -e '.[bench]')
needs_open3d = pytest.mark.skipif(
    importlib.util.find_spec("open3d") is None, reason="open3d not installed (the bench extra; .ci/run installs it)"
)


def _run(script: str, *args: str) -> dict:
    proc = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), *args],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


@needs_open3d
def test_along_track_finds_scene_0101s_frames_ahead_of_their_poses(sample_root):
    report = _run("along_track.py", "--sample", str(sample_root), "--scenes", "scene-0101")["scene-0101"]
    assert 0.0 < report["ape_rmse_m"] < 0.45
    assert report["moving_frames"] == 29
    # two GICPs at ground-truth poses: frames ahead along the track in most moving frames (docs/results.md, Accuracy)
    assert report["gt_map_along_share"] > 0 and report["open3d_along_share"] > 0
    assert report["open3d_frames_ahead"] > report["moving_frames"] / 2


def test_durable_state_resumes_with_and_without_a_snapshot():
    for frames in ("10", "25"):  # 10: no snapshot yet, the journal alone; 25: a snapshot at 20, then the journal
        report = _run("durable_state.py", "--scene", "", "--synthetic", "1", "--frames", frames)
        assert report["resume"]["poses_equal"] is True
        assert report["resume"]["journal_frames"] == (10 if frames == "10" else 5)
        assert (report["snapshot_mb"] > 0) == (frames == "25")


def test_working_map_counts_each_laps_voxels_at_every_lap_start():
    report = _run("working_map.py", "--frames", "200", "--blocks", "2x2", "--radius", "60")
    laps = report["laps"]
    assert [row["lap"] for row in laps] == [1, 2, "end"]
    for row in laps:
        assert sum(row["by_lap"]) == row["alive"] <= row["rows"] <= row["capacity"]
        assert row["later_within_layer_of_lap1"] <= row["later_laps"] == sum(row["by_lap"][1:])
    assert laps[0]["later_laps"] == 0 and laps[-1]["later_laps"] > 0


@needs_open3d
def test_coarse_lean_scores_every_stage_of_scene_0101s_frames(sample_root):
    # the source pick that leans: the first voxel of each block, the rear-most in the ego frame (the default leans no way)
    first_pick = str(Path(__file__).resolve().parents[2] / "benchmarks" / "configs" / "first_pick.json5")
    report = _run("coarse_lean.py", "--sample", str(sample_root), "--scenes", "scene-0101", "--config", first_pick)[
        "scene-0101"
    ]
    assert [row["frame"] for row in report["frames"]] == list(range(9, 40))
    assert report["moving_frames"] == 29 and report["slow_frames"] == 4
    # the slow start: coarse GICP leans ahead of where fine GICP from the guess lands, several times as far
    slow = report["mean_slow_cm"]
    assert slow["coarse"] > 2 * abs(slow["fine_only"])


def test_time_offset_reads_the_same_data_offset_from_four_runs_of_scene_0101(sample_root):
    report = _run("time_offset.py", "--sample", str(sample_root), "--scenes", "scene-0101")["scene-0101"]
    runs = report["runs"]
    assert list(runs) == ["forward", "reversed", "turned", "turned+rev"]
    shifts = [runs[r]["best_shift_ms"] for r in runs]
    # the four contrasts are the four shifts again, rotated: nothing lost in the decomposition
    assert (
        abs(
            report["data_offset_ms"]
            + report["ego_lead_ms"]
            + report["travel_lead_ms"]
            + report["residual_ms"]
            - shifts[0]
        )
        < 1e-6
    )
    # frames after their poses (docs/results.md): forward runs fit a later ground truth, reversed ones an earlier
    assert report["data_offset_ms"] > 0 and shifts[0] > shifts[1] and shifts[2] > shifts[3]
    assert all(runs[r]["ape_at_best_shift_m"] <= runs[r]["ape_rmse_m"] for r in runs)
    assert report["exact_odometry_ape_m"] > 0
