"""`occvo serve` and `occvo up` check their configuration before starting anything: a bad value, a listen endpoint
beyond loopback without authentication and access control, a store folder that is not there, each is one line on
stderr and exit code 2; relative paths are the current folder's; a worker that never comes up is never reported
ready."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from occvo_cli.cli import main
from occvo_services import defaults
from occvo_services.sessions import free_port

REPO = Path(__file__).resolve().parents[2]
WORKERS = ("inference_worker.json5", "registration_worker.json5", "map_service.json5")


def _config_dir(tmp: Path, **registration) -> Path:
    """The built-in worker configs, the registration worker's with `registration` set."""
    import json5

    tmp.mkdir(parents=True, exist_ok=True)
    for name in WORKERS:
        data = json5.loads(defaults.path(name).read_text())
        if name == "registration_worker.json5":
            data.update(registration)
        (tmp / name).write_text(json.dumps(data))
    return tmp


def _router(tmp: Path, endpoints: list[str], extra: str = "") -> Path:
    path = tmp / "router.json5"
    path.write_text(f'{{ mode: "router", listen: {{ endpoints: {json.dumps(endpoints)} }} {extra} }}')
    return path


def _one_line(capfd, code: int) -> str:
    out, err = capfd.readouterr()
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err and out == "", (code, out, err)
    return lines[0]


@pytest.mark.parametrize(
    "setting, words",
    [
        ({"tile_m": 1.0}, "tile_m"),
        ({"tile_m": 0.001}, "tile_m"),
        ({"max_rss_mb": 64}, "max_rss_mb=64"),
        ({"kernel_threads": 100000}, "kernel_threads"),
    ],
    ids=lambda v: str(v),
)
def test_a_bad_worker_value_is_one_line_and_exit_2(tmp_path, capfd, setting, words):
    cfg = _config_dir(tmp_path / "cfg", **setting)
    line = _one_line(capfd, main(["serve", "--config-dir", str(cfg), "--listen", f"tcp/127.0.0.1:{free_port()}"]))
    assert words in line, line


def test_every_listen_endpoint_is_checked(tmp_path, capfd):
    """A loopback endpoint first and a LAN one after it: the LAN one is refused without authentication, and with
    authentication but no access control."""
    lan = f"tcp/0.0.0.0:{free_port()}"
    plain = _router(tmp_path, [f"tcp/127.0.0.1:{free_port()}", lan])
    line = _one_line(capfd, main(["serve", "--router-config", str(plain)]))
    assert lan in line and "without authentication" in line, line
    users = tmp_path / "users.txt"
    users.write_text("a:b\n")
    auth = _router(
        tmp_path,
        [f"tcp/127.0.0.1:{free_port()}", lan],
        f", transport: {{ auth: {{ usrpwd: {{ dictionary_file: {json.dumps(str(users))} }} }} }}",
    )
    line = _one_line(capfd, main(["serve", "--router-config", str(auth)]))
    assert "no access control" in line, line


def test_a_missing_store_folder_is_one_line_and_exit_2(tmp_path, capfd):
    line = _one_line(capfd, main(["serve", "--store", str(tmp_path / "no" / "such" / "x.sqlite")]))
    assert "does not exist" in line, line


def test_relative_config_dir_is_the_current_folders(tmp_path, capfd, monkeypatch):
    _config_dir(tmp_path / "here", tile_m=1.0)
    monkeypatch.chdir(tmp_path)
    line = _one_line(capfd, main(["serve", "--config-dir", "here", "--listen", f"tcp/127.0.0.1:{free_port()}"]))
    assert str(tmp_path / "here") in line and "tile_m" in line, line


def test_up_checks_its_worker_configs(tmp_path, capfd):
    cfg = _config_dir(tmp_path / "cfg", max_rss_mb=64)
    up = tmp_path / "occvo.json5"
    worker = '{ role: "registration", config: "cfg/registration_worker.json5" }'
    up.write_text(f'{{ router: {{ listen: "tcp/127.0.0.1:{free_port()}" }}, workers: [ {worker} ] }}')
    line = _one_line(capfd, main(["up", "--config", str(up)]))
    assert "max_rss_mb=64" in line, line
    assert cfg.is_dir()


def test_a_worker_that_never_comes_up_is_not_reported_ready(tmp_path):
    """A registration worker that fails at start (its OccVO config is missing) restarts until --start-timeout:
    serve then stops with exit code 1, and no "worker ready" line names it."""
    cfg = _config_dir(tmp_path / "cfg", occvo_config=str(tmp_path / "missing.json5"), warm_up=False)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep))
    proc = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "serve", "--json", "--quiet", "--config-dir", str(cfg),
         "--listen", f"tcp/127.0.0.1:{free_port()}", "--start-timeout", "10"],
        capture_output=True, text=True, timeout=240, env=env, cwd=tmp_path,
    )  # fmt: skip
    events = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    ready = [e.get("role") for e in events if e.get("event") == "worker ready"]
    assert proc.returncode != 0, proc.stderr[-2000:]
    assert "registration" not in ready and not [e for e in events if e.get("event") == "ready"], events
