"""An occvo-out/ folder is evo-complete: the embedded default's run writes its ground truth beside the estimate and
run.json, and evo's own commands on those files give what `occvo eval` and `occvo eval --rpe` give, to 1e-6."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from occvo_cli.cli import main

pytest.importorskip("evo", reason="evo is in the dev extra")
STATS = ("rmse", "mean", "median", "std", "min", "max", "sse")


@pytest.fixture(scope="module")
def out(tmp_path_factory):
    out = tmp_path_factory.mktemp("run") / "occvo-out"
    assert main(["run", "--quiet", "--out", str(out)]) == 0
    return out


def _evo(tool: str, *args: str) -> dict:
    """evo's command line (evo_ape / evo_rpe), its statistics table parsed."""
    code = (
        f"import sys\ntry:\n    from evo.cli.entry_points import {tool}\nexcept ImportError:  # evo before 1.30\n"
        f"    from evo.entry_points import {tool}\nsys.argv[0] = 'evo_{tool}'\n{tool}()"
    )
    done = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    rows = [line.split("\t") for line in done.stdout.splitlines() if "\t" in line]
    return {k.strip(): float(v) for k, v in rows}


def _occvo_eval(capsys, *args: str) -> dict:
    capsys.readouterr()
    assert main(["eval", *args, "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_the_run_writes_its_ground_truth_and_run_json(out):
    from occvo_core.sim import SyntheticScene
    from occvo_core.trajectory import read_kitti, read_tum

    stamps, gt = read_tum(out / "groundtruth.tum")
    est_stamps, _ = read_tum(out / "trajectory.tum")
    np.testing.assert_array_equal(stamps, est_stamps)
    np.testing.assert_allclose(read_kitti(out / "groundtruth.kitti"), SyntheticScene(seed=0).gt_poses, atol=1e-8)
    np.testing.assert_allclose(gt, read_kitti(out / "groundtruth.kitti"), atol=1e-8)
    record = json.loads((out / "run.json").read_text())
    assert (
        record["occvo_version"]
        and record["command"] == f"occvo run --quiet --out {out}"
        and record["options"]["seed"] == 0
    )
    assert record["config"]["voxel_pfilter"]["enabled"] is True


@pytest.mark.parametrize(
    "tool,flags,evo_flags",
    [
        ("ape", [], ["-a"]),
        ("rpe", ["--rpe"], []),
        ("rpe", ["--rpe", "--delta", "2"], ["--delta", "2"]),
        ("rpe", ["--rpe", "--delta", "1", "--delta-unit", "m"], ["--delta", "1", "--delta_unit", "m"]),
    ],
)
def test_evo_agrees_with_occvo_eval(out, capsys, tool, flags, evo_flags):
    gt, est = str(out / "groundtruth.tum"), str(out / "trajectory.tum")
    theirs = _evo(tool, "tum", gt, est, *evo_flags)
    ours = _occvo_eval(capsys, "--gt", gt, "--est", est, *flags)
    for k in STATS:
        assert ours[k] == pytest.approx(theirs[k], abs=1e-6), k


def test_rpe_refuses_a_delta_that_leaves_no_pair(out, capsys):
    gt, est = str(out / "groundtruth.tum"), str(out / "trajectory.tum")
    assert main(["eval", "--gt", gt, "--est", est, "--rpe", "--delta", "1000", "--delta-unit", "m"]) == 2
    assert "leaves no pair" in capsys.readouterr().err
