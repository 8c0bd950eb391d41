"""Writers replace only what occvo wrote: an existing file of another kind or origin is refused (one line, exit 2, the
file untouched) unless --force; occvo's own MCAP, rerun recording, trajectory and tile are replaced as before. Files
written by the real writers."""

from __future__ import annotations

import numpy as np
import pytest

from occvo_cli.cli import main
from occvo_core.errors import ConfigError
from occvo_core.overwrite import check_replaceable
from occvo_core.trajectory import write_kitti, write_tum

FOREIGN = b"# my notes, not occvo's\nkeep me\n"


def _refused(capsys, code: int, flag: str) -> str:
    out, err = capsys.readouterr()
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, (code, out, err)
    assert flag in lines[0] and "--force" in lines[0] and "occvo wrote" in lines[0], lines[0]
    return lines[0]


def test_each_kind_is_told_by_its_content(tmp_path):
    poses = np.tile(np.eye(4), (3, 1, 1))
    write_kitti(tmp_path / "t.kitti", poses)
    write_tum(tmp_path / "t.tum", poses, np.arange(3.0))
    np.save(tmp_path / "tile.npy", np.zeros((5, 4)))
    np.save(tmp_path / "other.npy", np.zeros((5, 3), np.float32))
    (tmp_path / "empty.txt").write_bytes(b"")
    (tmp_path / "notes.txt").write_bytes(FOREIGN)
    for name, kind in (("t.kitti", "trajectory"), ("t.tum", "trajectory"), ("tile.npy", "npy"), ("empty.txt", "npy")):
        check_replaceable(tmp_path / name, kind, "--out")  # occvo's own, or empty: nothing to lose
    check_replaceable(tmp_path / "absent", "mcap", "--mcap")
    for name, kind in (("notes.txt", "trajectory"), ("other.npy", "npy"), ("t.kitti", "mcap"), ("t.tum", "rrd")):
        with pytest.raises(ConfigError, match="exists and is not"):
            check_replaceable(tmp_path / name, kind, "--out")
        check_replaceable(tmp_path / name, kind, "--out", force=True)
    with pytest.raises(ConfigError, match="is a folder"):
        check_replaceable(tmp_path, "trajectory", "--out", force=True)


def test_run_refuses_to_overwrite_a_foreign_file_and_replaces_its_own(tmp_path, capsys):
    """--mcap and --rerun of `occvo run`: a foreign file refused and untouched; --force replaces it with a recording
    that is occvo's, so the next run replaces it without --force."""
    pytest.importorskip("foxglove")
    pytest.importorskip("rerun")
    for flag, name in (("--mcap", "run.mcap"), ("--rerun", "run.rrd")):
        path, out = tmp_path / name, tmp_path / name.replace(".", "-")
        base = ["run", "--quiet", "--frames", "3", "--out", str(out)]
        path.write_bytes(FOREIGN)
        _refused(capsys, main([*base, flag, str(path)]), flag)
        assert path.read_bytes() == FOREIGN and not out.exists()  # refused before the run
        assert main([*base, flag, str(path), "--force"]) == 0
        written = path.read_bytes()
        assert written != FOREIGN and len(written) > 1000
        check_replaceable(path, "mcap" if flag == "--mcap" else "rrd", flag)  # now occvo's
        assert main([*base, flag, str(path)]) == 0  # its own: replaced without --force
        capsys.readouterr()


@pytest.mark.parametrize(
    "argv, flag",
    [
        (["replay", "synthetic:0", "--frames", "2", "--out"], "--out"),
        (["replay", "synthetic:0", "--frames", "2", "--tum"], "--tum"),
        (["tile", "0", "0", "--out"], "--out"),
        (["store", "export", "car0", "--store", "absent.sqlite", "--out"], "--out"),
    ],
    ids=["replay --out", "replay --tum", "tile --out", "store export --out"],
)
def test_service_commands_refuse_a_foreign_file_before_they_start(tmp_path, capsys, argv, flag):
    """Refused before any connection or store is opened: no router, no store needed to see it."""
    path = tmp_path / ("notes.npy" if argv[0] == "tile" else "notes.txt")
    path.write_bytes(FOREIGN)
    nowhere = [] if argv[0] == "store" else ["--connect", "tcp/127.0.0.1:1"]
    _refused(capsys, main([*argv, str(path), *nowhere]), flag)
    assert path.read_bytes() == FOREIGN
