"""Every server the project starts listens on loopback unless told: `occvo view --web-port` (rerun's web viewer and
its data server), `--foxglove` (the WebSocket server); `--bind 0.0.0.0` widens them. Read from the kernel's own
table of listening sockets (/proc/net/tcp, tcp6)."""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from occvo_services.sessions import free_port, open_router

pytest.importorskip("rerun")


def _listening(port: int) -> set[str]:
    """The local addresses a TCP socket listens on at `port`."""
    found = set()
    for table, family in (("/proc/net/tcp", socket.AF_INET), ("/proc/net/tcp6", socket.AF_INET6)):
        for line in Path(table).read_text().splitlines()[1:]:
            local, state = line.split()[1], line.split()[3]
            addr, hexport = local.split(":")
            if state == "0A" and int(hexport, 16) == port:  # 0A: LISTEN
                raw = bytes.fromhex(addr)
                # the kernel prints each 32-bit word in host (little-endian) order
                raw = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))
                found.add(socket.inet_ntop(family, raw))
    return found


def _free_pair() -> int:
    """A port P with P + 1 free too (the web viewer and its data)."""
    for _ in range(50):
        p = free_port()
        with socket.socket() as s:
            try:
                s.bind(("127.0.0.1", p + 1))
            except OSError:
                continue
        return p
    raise RuntimeError("no two free ports in a row")


@pytest.mark.parametrize("bind, want", [(None, {"127.0.0.1"}), ("0.0.0.0", {"0.0.0.0"})])
def test_the_web_viewer_and_its_data_listen_on_loopback_unless_told(bind, want):
    from occvo_core.viz.rerun_log import RerunView

    port = _free_pair()
    view = RerunView.open("occvo-listeners", web_port=port, **({"bind": bind} if bind else {}))
    try:
        assert _listening(port) == want and _listening(port + 1) == want
    finally:
        view.close()
    assert _listening(port) == set() and _listening(port + 1) == set()  # the server ends with the view


@pytest.mark.parametrize("bind, want", [(None, {"127.0.0.1"}), ("0.0.0.0", {"0.0.0.0"})])
def test_occvo_view_serves_on_loopback_unless_bind_widens_it(bind, want):
    """The command itself: --web-port and --foxglove, each listener checked while it runs."""
    pytest.importorskip("foxglove")
    endpoint, web, fox = f"tcp/127.0.0.1:{free_port()}", _free_pair(), free_port()
    router = open_router(endpoint)
    argv = [sys.executable, "-m", "occvo_cli", "view", "--connect", endpoint, "--stream", "car0", "--seconds", "60"]
    argv += ["--web-port", str(web), "--foxglove", str(fox), *(["--bind", bind] if bind else [])]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        lines = [proc.stdout.readline(), proc.stdout.readline()]  # the web viewer's URL, then Foxglove's
        assert lines[0].startswith("web viewer: http://127.0.0.1:") and lines[1].startswith("foxglove: ws://"), (
            lines,
            proc.stderr.read() if proc.poll() is not None else "",
        )
        deadline = time.monotonic() + 10
        while _listening(fox) != want and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _listening(web) == want and _listening(web + 1) == want and _listening(fox) == want
    finally:
        proc.terminate()
        proc.communicate(timeout=60)
        router.close()
    assert proc.returncode == 0


def test_the_kernel_table_is_read_right():
    """The check itself: a socket of this test, on loopback and on every interface."""
    for host in ("127.0.0.1", "0.0.0.0"):
        with socket.socket() as s:
            s.bind((host, 0))
            s.listen()
            assert _listening(s.getsockname()[1]) == {host}
