"""A worker started before its router (systemd or a script starting both) waits for it instead of exiting; one
that never comes, or a listener that is no router, ends it with one line."""

from __future__ import annotations

import signal
import socket
import subprocess
import sys
import time

from occvo_schemas import keys
from occvo_services.sessions import free_port, open_router, open_session


def _map_service(endpoint: str, *extra: str) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "occvo_services.map_service", "--connect", endpoint, "--worker-id", "map-wait", *extra]
    return subprocess.Popen(cmd, stderr=subprocess.PIPE, text=True)


def _line_with(proc: subprocess.Popen, text: str, lines: list[str]) -> None:
    while not any(text in line for line in lines):
        line = proc.stderr.readline()
        assert line, "".join(lines)  # the worker ended before it logged `text`
        lines.append(line)


def test_a_worker_started_before_its_router_waits_and_comes_up_with_it():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = _map_service(endpoint)
    lines: list[str] = []
    router = client = None
    try:
        _line_with(proc, "waiting for the router", lines)
        assert proc.poll() is None and f"no router at {endpoint}" in lines[-1]
        router = open_router(endpoint)
        client = open_session(endpoint, pick_up=False)
        deadline = time.monotonic() + 60
        alive: list[str] = []
        while not alive and time.monotonic() < deadline:
            alive = [str(r.ok.key_expr) for r in client.liveliness().get(keys.alive("map"), timeout=1.0) if r.ok]
            time.sleep(0.2)
        assert alive == [keys.alive("map", "map-wait")]
    finally:
        proc.send_signal(signal.SIGTERM)
        rest = proc.communicate(timeout=60)[1]
        for s in (client, router):
            if s is not None:
                s.close()
    assert proc.returncode == 0, rest
    assert "".join(lines + [rest]).count("waiting for the router") == 1  # told once, not at every try


def test_no_router_within_the_wait_is_one_line_and_exit_1():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    proc = _map_service(endpoint, "--router-wait-s", "1", "--log-level", "WARNING")
    err = proc.communicate(timeout=60)[1]
    assert proc.returncode == 1 and err.count("\n") == 1, err
    assert err.startswith("python -m occvo_services.map_service: no router at " + endpoint)


def test_a_shutdown_while_waiting_ends_the_worker_cleanly():
    proc = _map_service(f"tcp/127.0.0.1:{free_port()}")
    lines: list[str] = []
    _line_with(proc, "waiting for the router", lines)
    proc.send_signal(signal.SIGTERM)
    rest = proc.communicate(timeout=30)[1]
    assert proc.returncode == 0 and "Traceback" not in rest, rest


def test_a_listener_that_is_no_router_is_not_waited_for():
    """Something answers at the endpoint but opens no session (a wrong port, a router refusing the worker): waiting
    would not help, so the worker says so at once, well within its wait."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen()
        endpoint = f"tcp/127.0.0.1:{listener.getsockname()[1]}"
        proc = _map_service(endpoint, "--router-wait-s", "600", "--log-level", "WARNING")
        err = proc.communicate(timeout=300)[1]  # a worker that waited would still be waiting here
    assert proc.returncode == 1 and err.count("\n") == 1 and "refused a session" in err, err
