"""run.json says what made an output folder: the git commit of the checkout occvo runs from (null outside one), a
digest of the input (its frame files, or the synthetic scene's parameters) and the versions of numpy, numba, torch
and zenoh."""

from __future__ import annotations

import json
import shutil
import subprocess
from importlib.metadata import version
from pathlib import Path

import numpy as np
import pytest

from occvo_cli.cli import main
from occvo_cli.run_record import git_commit

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> Path:
    from occvo_core.datasets.occvo_release import write_release_scene
    from occvo_core.sim import SyntheticScene

    s = SyntheticScene(seed=0, frames=4)
    return write_release_scene(tmp_path_factory.mktemp("rec"), "four", [s[i] for i in range(4)], s.gt_poses[:4])


def _record(out: Path, *argv: str) -> dict:
    assert main(["run", "--quiet", "--out", str(out), *argv]) == 0
    return json.loads((out / "run.json").read_text())


def test_run_json_names_the_commit_and_the_libraries(tmp_path, capsys):
    record = _record(tmp_path / "o", "--frames", "2")
    head = subprocess.run(["git", "-C", str(REPO), "rev-parse", "HEAD"], capture_output=True, text=True, check=False)
    if head.returncode != 0:
        pytest.skip(f"{REPO} is not a git checkout: {head.stderr.strip()}")
    assert record["git_commit"] == head.stdout.strip() and isinstance(record["git_dirty"], bool)
    assert record["libraries"] == {
        "numpy": version("numpy"),
        "numba": version("numba"),
        "torch": version("torch"),
        "zenoh": version("eclipse-zenoh"),
    }
    assert record["input_digest"]["over"] == "synthetic scene parameters"


def test_no_commit_outside_a_checkout(tmp_path):
    assert git_commit(tmp_path) == {"git_commit": None, "git_dirty": None}
    inside = tmp_path / "project" / "site-packages"  # an installed copy inside another project's checkout
    inside.mkdir(parents=True)
    subprocess.run(["git", "init", "-q", str(tmp_path / "project")], check=True)
    assert git_commit(inside) == {"git_commit": None, "git_dirty": None}


def test_the_input_digest_follows_the_frames_and_nothing_else(scene, tmp_path, capsys):
    first = _record(tmp_path / "a", "--input", str(scene))["input_digest"]
    assert first["over"] == "frame files" and first["frames"] == 4 and len(first["sha256"]) == 64
    moved = tmp_path / "elsewhere" / "renamed"
    shutil.copytree(scene, moved)
    assert _record(tmp_path / "b", "--input", str(moved), "--threads", "1")["input_digest"] == first
    assert _record(tmp_path / "c", "--input", str(moved), "--frames", "3")["input_digest"]["sha256"] != first["sha256"]
    frame = np.load(moved / "2.npy")
    frame[0, 0] += 0.4  # one voxel a grid step over
    np.save(moved / "2.npy", frame)
    assert _record(tmp_path / "d", "--input", str(moved))["input_digest"]["sha256"] != first["sha256"]


def test_the_synthetic_digest_follows_the_scene_parameters(tmp_path, capsys):
    a = _record(tmp_path / "a", "--frames", "2", "--seed", "3")["input_digest"]
    assert _record(tmp_path / "b", "--frames", "2", "--seed", "3", "--threads", "1")["input_digest"] == a
    assert _record(tmp_path / "c", "--frames", "2", "--seed", "4")["input_digest"]["sha256"] != a["sha256"]
    assert a["seed"] == 3 and a["frames"] == 2 and a["noise"] == "default"
