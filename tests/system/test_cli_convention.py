"""The `occvo` command's convention, command by command: a bad argument exits 2 and a missing router 1, each with
exactly one line on stderr, no traceback and nothing on stdout; --json output parses; a run failing its success rule
exits 1; unreadable frames stop a run (exit 2) unless --skip-bad-frames."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from occvo_cli.cli import main
from occvo_services.sessions import free_port

REPO = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Two maps 1 km apart (no frame holds both), one beside the first, and a tiny release scene."""
    from occvo_core.datasets.occvo_release import write_release_scene
    from occvo_core.map_metrics import save_map
    from occvo_core.sim import SyntheticScene

    d = tmp_path_factory.mktemp("cli")
    pts = np.random.default_rng(0).uniform(0, 20, (500, 3))
    save_map(d / "est.npz", pts, np.full(500, 15))
    save_map(d / "near.npz", pts + 0.1, np.full(500, 15))
    save_map(d / "far.npz", pts + [1000.0, 0, 0], np.full(500, 15))
    s = SyntheticScene(seed=0, frames=5)
    write_release_scene(d, "five", [s[i] for i in range(5)], s.gt_poses[:5])
    return d


def _no_router() -> list[str]:
    return ["--connect", f"tcp/127.0.0.1:{free_port()}"]


BAD_INPUT = [
    ["run", "--frames", "x"],
    ["run", "--input", "/no/such/scene"],
    ["run", "--from-images", "--checkpoint", "/no/such/checkpoint.pt"],
    ["run", "--from-images", "--mask", "lidar"],
    ["eval", "--gt", "/no/gt.kitti", "--est", "/no/est.kitti"],
    ["ablation"],
    ["eval-map", "--est-map", "/no/map.npz", "--gt-map", "/no/gt.npz"],
    ["eval-map", "--est-map", "{d}/est.npz", "--gt-map", "{d}/far.npz"],
    ["eval-map", "--est-map", "{d}/est.npz", "--reference-scene", "{d}/occupancy/five"],
    ["train-occ", "--minutes", "0", "--out", "{d}/train"],
    ["eval-occ", "--checkpoint", "/no/checkpoint.pt"],
    ["eval-occ", "--input", "/no/such/drive"],
    ["eval-occ", "--input", "/no/such/drive", "--labels", "{d}"],
    ["make-occupancy", "--input", "/no/such/drive", "--out", "{d}/occ3d"],
    ["make-occupancy", "--input", "/no/such/drive", "--keyframes", "4-2", "--out", "{d}/occ3d"],
    ["serve", "--registration-workers", "0"],
    ["up", "--config", "/no/occvo.json5"],
    ["replay", "synthetic:x"],
    ["poses", "--stream", "no spaces"],
    ["tile", "1.5", "2"],
    ["map-info", "--no-such-flag"],
]
NO_ROUTER = [["replay", "synthetic:0", "--frames", "2"], ["poses"], ["tile", "0", "0"], ["map-info"]]


def _check_one_line(code, out, err, want):
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == want, err
    assert len(lines) == 1 and "Traceback" not in err, err
    assert out == "", out
    return lines[0]


@pytest.mark.parametrize("argv", BAD_INPUT, ids=lambda a: " ".join(a[:2]))
def test_bad_input_is_one_line_and_exit_code_2(argv, files, capfd):
    argv = [a.format(d=files) for a in argv]
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's usage errors
        code = exc.code
    out, err = capfd.readouterr()
    line = _check_one_line(code, out, err, 2)
    assert line.startswith("occvo")


@pytest.mark.parametrize("argv", NO_ROUTER, ids=lambda a: a[0])
def test_no_router_is_one_line_and_exit_code_1(argv, capfd):
    code = main(argv + _no_router() + (["--quiet"] if argv[0] == "replay" else []))
    out, err = capfd.readouterr()
    line = _check_one_line(code, out, err, 1)
    assert "no router at tcp/127.0.0.1:" in line and "occvo serve" in line and "--connect" in line


def test_eval_map_refusals_name_what_to_do(files, capfd):
    assert main(["eval-map", "--est-map", str(files / "est.npz"), "--gt-map", str(files / "far.npz")]) == 2
    assert "do not overlap" in capfd.readouterr().err
    assert (
        main(["eval-map", "--est-map", str(files / "est.npz"), "--reference-scene", str(files / "occupancy" / "five")])
        == 2
    )
    assert "give --est-traj" in capfd.readouterr().err
    assert main(["eval-map", "--est-map", str(files / "est.npz"), "--gt-map", str(files / "near.npz"), "--json"]) == 0
    assert json.loads(capfd.readouterr().out)["precision"] == 1.0


def _occvo(*argv, **kw):
    return subprocess.run(
        [sys.executable, "-m", "occvo_cli", *argv],
        check=False,
        capture_output=True,
        text=True,
        env=ENV,
        timeout=600,
        **kw,
    )


def test_a_real_process_keeps_the_convention():
    assert _occvo("--version").stdout.startswith("occvo ")
    bad = _occvo("replay", "synthetic:0", "--window", "0")
    _check_one_line(bad.returncode, bad.stdout, bad.stderr, 2)
    gone = _occvo("poses", *_no_router())
    _check_one_line(gone.returncode, gone.stdout, gone.stderr, 1)
    debug = _occvo("poses", "--debug", *_no_router())
    assert debug.returncode == 1 and "Traceback" in debug.stderr


def test_run_json_is_one_json_document_on_stdout(tmp_path):
    out = tmp_path / "out"
    proc = _occvo("run", "--frames", "5", "--out", str(out), "--json")  # progress on stderr, JSON alone on stdout
    assert proc.returncode == 0, proc.stderr
    tool = subprocess.run(
        [sys.executable, "-m", "json.tool"], check=False, input=proc.stdout, capture_output=True, text=True
    )
    assert tool.returncode == 0, proc.stdout
    summary = json.loads(proc.stdout)
    assert summary["frames"] == 5 and summary["compile_s"] >= 0 and summary["success"] is True
    assert json.loads((out / "summary.json").read_text())["ms_per_frame_median"] == summary["ms_per_frame_median"]
    # the map's voxel count is the map a user gets (map.npz: the persistent voxels), of the live ones (map_voxels.npz)
    assert summary["map_voxels"] == len(np.load(out / "map.npz")["points"])
    live = np.load(out / "map_voxels.npz")
    assert summary["live_voxels"] == len(live["points"]) and summary["map_voxels"] == live["persistent"].sum()


def test_unreadable_frames_stop_the_run_unless_skipped(files, tmp_path):
    scene = tmp_path / "scene"
    scene.mkdir()
    for i in range(5):
        (scene / f"{i}.npy").write_bytes((files / "occupancy" / "five" / f"{i}.npy").read_bytes())
    (scene / "2.npy").write_bytes(b"")  # 0 bytes
    (scene / "3.npy").write_text("x y z label\n")  # text named .npy
    stop = _occvo("run", "--input", str(scene), "--out", str(tmp_path / "a"), "--quiet")
    line = _check_one_line(stop.returncode, stop.stdout, stop.stderr, 2)
    assert "frame 2" in line and "2.npy" in line and "unreadable" in line
    skip = _occvo("run", "--input", str(scene), "--out", str(tmp_path / "b"), "--quiet", "--skip-bad-frames", "--json")
    assert skip.returncode == 0, skip.stderr
    assert json.loads(skip.stdout)["frames"] == 3
    assert len(json.loads((tmp_path / "b" / "summary.json").read_text())["skipped_frames"]) == 2


def test_a_run_failing_its_success_rule_exits_1(files, tmp_path):
    from occvo_core.trajectory import read_trajectory, write_kitti

    gt = read_trajectory(files / "trajectory" / "five.kitti")
    gt[:, :3, 3] *= 5.0  # no rigid alignment maps the estimate onto a drive five times as long
    write_kitti(tmp_path / "wrong.kitti", gt)
    proc = _occvo(
        "run",
        "--input",
        str(files / "occupancy" / "five"),
        "--gt",
        str(tmp_path / "wrong.kitti"),
        "--out",
        str(tmp_path / "o"),
        "--quiet",
    )
    line = _check_one_line(proc.returncode, "", proc.stderr, 1)
    assert "success rule" in line
    assert json.loads((tmp_path / "o" / "summary.json").read_text())["success"] is False


def test_serve_on_a_port_another_program_holds_says_so_in_one_line():
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = _occvo("serve", "--listen", f"tcp/127.0.0.1:{port}", "--quiet")
    assert proc.returncode == 1, proc.stderr
    lines = proc.stderr.splitlines()
    assert len(lines) == 1 and "the router could not listen on" in lines[0] and "--listen" in lines[0], proc.stderr
