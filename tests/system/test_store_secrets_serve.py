"""`occvo serve` on a PostgreSQL store whose role needs a password, given in OCCVO_STORE_URL: the password is in no
`ps` line of serve or of any process it starts, in no log file, in no error event sent to a client (the database
stopped mid-drive: `store_unavailable`); written on the command line it is refused (one line, exit 2); a store that cannot be
reached at start is one line and exit 2 within 10 s, no worker started (`occvo serve` and `occvo up`)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from occvo_cli.cli import main
from occvo_services.sessions import free_port
from occvo_services.store.url import STORE_URL_ENV

REPO = Path(__file__).resolve().parents[2]
PASSWORD = "pw-Serve@42"
SECRET = "pw-Serve%4042"  # as the URL holds it


def _env(**extra) -> dict[str, str]:
    path = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
    return {**os.environ, "PYTHONPATH": path, **extra}


def _tree(pid: int) -> list[int]:
    """pid and every process under it."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        for task in Path(f"/proc/{p}/task").glob("*"):
            try:
                todo += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                pass
    return out


def _clean(text: str, where: str) -> None:
    assert SECRET not in text and PASSWORD not in text and "Serve@42" not in text, f"the password in {where}"


def _one_line_exit_2(cmd: list[str], env: dict, limit_s: float = 10.0) -> str:
    t0 = time.monotonic()
    out = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    took = time.monotonic() - t0
    lines = [line for line in out.stderr.splitlines() if line.strip()]
    assert out.returncode == 2 and len(lines) == 1 and out.stdout == "", (out.returncode, out.stdout, out.stderr)
    assert took < limit_s, took
    _clean(out.stderr, "the error line")
    return lines[0]


def test_serve_keeps_the_store_password_out_of_ps_logs_and_events(tmp_path, pg_cluster, scene):
    from occvo_services.client import OccVOClient

    pg_cluster.add_password_user("occvo_serve", PASSWORD)
    db = pg_cluster.new_database().rsplit("/", 1)[1]
    # the query form: before, it reached the workers' logs and the clients' error events as it was
    url = f"postgresql://occvo_serve@127.0.0.1:{pg_cluster.port}/{db}?password={SECRET}"
    endpoint, logs = f"tcp/127.0.0.1:{free_port()}", tmp_path / "logs"
    err = open(tmp_path / "serve.err", "w")  # noqa: SIM115 - closed in finally, after the process
    proc = subprocess.Popen(
        [sys.executable, "-m", "occvo_cli", "serve", "--listen", endpoint, "--json", "--log-dir", str(logs)],
        cwd=REPO,
        env=_env(**{STORE_URL_ENV: url}),
        stdout=subprocess.PIPE,
        stderr=err,
        text=True,
    )
    out = []
    try:
        while not out or out[-1]["event"] != "ready":  # listening, each worker, ready (the store opened by each)
            line = proc.stdout.readline()
            assert line, (tmp_path / "serve.err").read_text()
            out.append(json.loads(line))
        pids = _tree(proc.pid)
        assert len(pids) >= 5  # serve, router, inference, registration, map service
        for pid in pids:
            _clean(Path(f"/proc/{pid}/cmdline").read_text(), f"the command line of {pid}")
        ps = subprocess.run(["ps", "-ww", "-o", "pid=,args=", "-p", ",".join(map(str, pids))], capture_output=True)
        assert len(ps.stdout.decode().splitlines()) == len(pids)
        _clean(ps.stdout.decode(), "ps")
        with OccVOClient(endpoint, "car", resend_after=1.0) as client:
            client.reset()
            for frame in scene[:3]:
                client.step(frame)
            pg_cluster.stop()
            try:
                client.publish(scene[3])
                with client._cv:
                    assert client._cv.wait_for(lambda: any(e.code == "store_unavailable" for e in client.errors), 60)
            finally:
                pg_cluster.start()
            client.wait_pose(3, timeout=120)
            refused = [e.message for e in client.errors if e.code == "store_unavailable"]
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=120)
        err.close()
    assert proc.returncode == 0
    for message in refused:
        _clean(message, "a store_unavailable event")
    assert any(f"occvo_serve@127.0.0.1:{pg_cluster.port}/{db}?password=***" in m for m in refused), refused
    files = [*logs.glob("*.log"), tmp_path / "serve.err"]
    assert {f.name for f in files} >= {"registration.log", "map.log", "inference.log", "router.log"}
    for f in files:
        _clean(f.read_text(), str(f))
    _clean(json.dumps(out) + rest, "serve's stdout")
    assert "?password=***" in (logs / "registration.log").read_text()  # the store named, the password not


def test_a_password_on_the_command_line_is_refused(tmp_path, capfd):
    url = f"postgresql://occvo:{SECRET}@127.0.0.1:{free_port()}/occvo"
    for argv in (["serve", "--store", url], ["store", "list", "--store", url]):
        assert main(argv) == 2
        out, err = capfd.readouterr()
        lines = err.strip().splitlines()
        assert len(lines) == 1 and out == "" and "occvo:***@" in lines[0], err
        assert all(w in lines[0] for w in ("OCCVO_STORE_URL", "--store-url-file", "PGPASSFILE")), lines[0]
        _clean(err, "the error line")
    config = tmp_path / "occvo.json5"
    config.write_text(json.dumps({"workers": [{"role": "registration", "args": ["--store-url", url]}]}))
    line = _one_line_exit_2([sys.executable, "-m", "occvo_cli", "up", "--config", str(config)], _env())
    assert "registration worker args: --store-url postgresql://occvo:***@" in line, line


def test_an_unreachable_store_at_start_is_one_line_and_exit_2(tmp_path):
    """serve (the URL in the environment, or in a URL file) and up (the URL in a worker's environment): the store
    named without its password and why, within 10 s; no worker ever started (no log file)."""
    pytest.importorskip("psycopg", reason="the PostgreSQL driver is not installed (pip install -e '.[postgres]')")
    url = f"postgresql://occvo:{SECRET}@127.0.0.1:{free_port()}/occvo"
    logs = tmp_path / "logs"
    serve = [sys.executable, "-m", "occvo_cli", "serve", "--listen", f"tcp/127.0.0.1:{free_port()}"]
    line = _one_line_exit_2([*serve, "--log-dir", str(logs)], _env(**{STORE_URL_ENV: url}))
    assert line.startswith("occvo serve: error: store postgresql://occvo:***@127.0.0.1:") and "refused" in line, line
    url_file = tmp_path / "store.url"
    url_file.write_text(url + "\n")
    url_file.chmod(0o600)
    line = _one_line_exit_2([*serve, "--store-url-file", str(url_file)], _env())
    assert "occvo:***@127.0.0.1" in line and "unreachable" in line, line
    config = tmp_path / "occvo.json5"
    config.write_text(json.dumps({"workers": [{"role": "map", "env": {STORE_URL_ENV: url}}]}))
    line = _one_line_exit_2(
        [sys.executable, "-m", "occvo_cli", "up", "--config", str(config), "--log-dir", str(logs)], _env()
    )
    assert line.startswith("occvo up: error: store postgresql://occvo:***@127.0.0.1:") and "unreachable" in line
    assert not logs.exists() or not any(logs.iterdir())


def test_store_commands_take_the_url_from_a_file_readable_by_its_owner_alone(tmp_path, pg_cluster, capfd):
    pg_cluster.add_password_user("occvo_file", PASSWORD)
    url_file = tmp_path / "store.url"
    db = pg_cluster.new_database().rsplit("/", 1)[1]
    url_file.write_text(f"postgresql://occvo_file:{SECRET}@127.0.0.1:{pg_cluster.port}/{db}\n")
    url_file.chmod(0o640)
    assert main(["store", "list", "--store-url-file", str(url_file)]) == 2
    assert "readable by others (mode 0640): chmod 600" in capfd.readouterr().err
    url_file.chmod(0o600)
    assert main(["store", "list", "--store-url-file", str(url_file), "--json"]) == 0
    out, err = capfd.readouterr()
    assert json.loads(out) == {"streams": []} and err == ""


@pytest.fixture(autouse=True)
def _no_store_in_the_environment(monkeypatch):
    """The tests name their stores themselves."""
    monkeypatch.delenv(STORE_URL_ENV, raising=False)
