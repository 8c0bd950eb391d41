"""Every bad argument exits 2 with one line naming it, before any work: paths that cannot be written, a mistyped flag
(named with its command and the flag probably meant), --gt without a scene; --frames N runs the first N frames of an
--input scene."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from occvo_cli.cli import main

REPO = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))


@pytest.fixture(scope="module")
def places(tmp_path_factory):
    """A folder holding a file, a folder, and a five-frame release scene."""
    from occvo_core.datasets.occvo_release import write_release_scene
    from occvo_core.sim import SyntheticScene

    d = tmp_path_factory.mktemp("args")
    (d / "file").write_text("x\n")
    (d / "folder").mkdir()
    s = SyntheticScene(seed=0, frames=5)
    write_release_scene(d, "five", [s[i] for i in range(5)], s.gt_poses[:5])
    return d


BAD_PATHS = [
    (["run", "--out", "{d}/file"], "--out"),
    (["run", "--mcap", "{d}/folder"], "--mcap"),
    (["run", "--mcap", "{d}/file/run.mcap"], "--mcap"),
    (["run", "--rerun", "{d}/folder"], "--rerun"),
    (["run", "--ros2-bag", "{d}/file/bag"], "--ros2-bag"),
    (["ablation", "--seeds", "0", "--out", "{d}/no-such-folder/rows.json"], "--out"),
    (["eval-occ", "--out", "{d}/folder"], "--out"),
    (["train-occ", "--minutes", "1", "--out", "{d}/file"], "--out"),
    (["train-occ", "--minutes", "1", "--out", "{d}/t", "--cache", "{d}/file"], "--cache"),
    (["replay", "synthetic:0", "--out", "{d}/folder"], "--out"),
    (["replay", "synthetic:0", "--tum", "{d}/file/t.tum"], "--tum"),
    (["tile", "0", "0", "--out", "{d}/folder"], "--out"),
    (["view", "--mcap", "{d}/folder"], "--mcap"),
    (["store", "export", "car0", "--store", "{d}/s.db", "--out", "{d}/folder"], "--out"),
    (["make-occupancy", "--input", "{d}/folder", "--out", "{d}/file"], "--out"),
    (["make-occupancy", "--input", "{d}/folder", "--out", "{d}/o", "--pictures", "{d}/file/p"], "--pictures"),
]


def _code_and_line(argv, capfd) -> tuple[int, str]:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    out, err = capfd.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert out == "" and len(lines) == 1 and "Traceback" not in err, (out, err)
    return code, lines[0]


@pytest.mark.parametrize("argv,flag", BAD_PATHS, ids=lambda a: " ".join(a) if isinstance(a, list) else a)
def test_a_path_that_cannot_be_written_is_a_bad_argument(argv, flag, places, capfd):
    before = sorted(places.rglob("*"))
    code, line = _code_and_line([a.format(d=places) for a in argv], capfd)
    assert code == 2, line
    command = " ".join(argv[:2]) if argv[0] == "store" else argv[0]
    assert line.startswith(f"occvo {command}: error: argument {flag}") and str(places) in line, line
    assert sorted(places.rglob("*")) == before  # refused before anything was written


def test_a_mistyped_flag_names_the_command_and_the_flag_meant(capfd):
    code, line = _code_and_line(["run", "--inputt", "X"], capfd)
    assert code == 2
    assert line.startswith("occvo run: error: unrecognized argument --inputt (did you mean --input?)"), line
    code, line = _code_and_line(["tile", "0", "0", "--jsn", "--frobnicate=3"], capfd)
    assert code == 2
    assert "occvo tile: error: unrecognized arguments --jsn (did you mean --json?), --frobnicate " in line, line
    code, line = _code_and_line(["run", "stray"], capfd)
    assert code == 2 and line.startswith("occvo run: error: unrecognized arguments: stray"), line


def test_gt_without_a_scene_is_a_bad_argument(capfd):
    code, line = _code_and_line(["run", "--gt", "/no/gt.kitti", "--frames", "2"], capfd)
    assert code == 2 and "--gt" in line and "--input" in line, line


def test_a_real_process_refuses_an_out_that_is_a_file(places):
    proc = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "run", "--out", str(places / "file")],
        capture_output=True,
        text=True,
        env=ENV,
        timeout=300,
        check=False,
    )
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr
    assert proc.stderr.splitlines() == [
        f"occvo run: error: argument --out: {places / 'file'} is a file, not a folder: name a folder "
        "(see occvo run --help)"
    ]


def test_frames_takes_the_first_frames_of_an_input_scene(places, tmp_path, capsys):
    from occvo_core.trajectory import read_trajectory

    scene = places / "occupancy" / "five"
    assert main(["run", "--input", str(scene), "--frames", "3", "--out", str(tmp_path / "three"), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["frames"] == 3
    three = read_trajectory(tmp_path / "three" / "trajectory.kitti")
    assert len(three) == 3 and len(read_trajectory(tmp_path / "three" / "groundtruth.kitti")) == 3
    assert main(["run", "--input", str(scene), "--out", str(tmp_path / "all"), "--quiet"]) == 0
    capsys.readouterr()
    every = read_trajectory(tmp_path / "all" / "trajectory.kitti")
    assert len(every) == 5
    np.testing.assert_array_equal(three, every[:3])  # the same frames, registered the same way
    assert main(["run", "--input", str(scene), "--frames", "0", "--out", str(tmp_path / "none")]) == 2
    assert "--frames must be a positive integer" in capsys.readouterr().err
