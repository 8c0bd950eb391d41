"""The wheel as a new user gets it: built from the package sources alone, installed into a fresh virtual environment
outside the checkout, run from an empty directory: --version, `occvo run` (the embedded default scene), and `occvo
serve` with replay, poses, tile and map-info against it, then SIGINT; every process exits 0.

The environment reuses this interpreter's site-packages (torch, open3d, numba, zenoh: no downloads) and gets the wheel
with --no-deps. `pytest -m packaging` selects it; it takes minutes (the fresh install compiles its kernels once).
"""

from __future__ import annotations

import getpass
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytestmark = [pytest.mark.packaging, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[2]
SOURCES = ["pyproject.toml", "README.md", "occvo_core", "occvo_cli", "services", "schemas"]
PACKAGES = ["occvo_core", "occvo_cli", "occvo_services", "occvo_schemas"]


@pytest.fixture(scope="module")
def venv(tmp_path_factory) -> Path:
    """A fresh virtual environment with the wheel installed; returns its bin folder."""
    root = tmp_path_factory.mktemp("packaging")
    src = root / "src"  # the package sources alone: a build must not need anything else of the checkout
    src.mkdir()
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(REPO / name, src / name)
    return install_in_fresh_venv(src, root)


def install_in_fresh_venv(src: Path, root: Path) -> Path:
    """The wheel built from the sources in src (pip, no dependencies, no build isolation), installed into a fresh
    virtual environment under root; returns its bin folder."""
    wheels = root / "wheels"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", str(wheels), str(src)],
        check=True,
        env=_clean_env(),
        cwd=root,
        timeout=600,
    )
    (wheel,) = wheels.glob("occvo-*.whl")
    env_dir = root / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--system-site-packages", str(env_dir)], check=True, timeout=300)
    _see_this_interpreters_packages(env_dir)
    subprocess.run(
        [str(env_dir / "bin" / "python"), "-m", "pip", "install", "-q", "--no-deps", str(wheel)],
        check=True,
        env=_clean_env(),
        cwd=root,
        timeout=600,
    )
    return env_dir / "bin"


def _see_this_interpreters_packages(env_dir: Path) -> None:
    """A venv made from a venv is based on the base interpreter: --system-site-packages shows it the base's
    site-packages, not this one's (where torch, zenoh and numba may live). A .pth adds this interpreter's site folders
    after the new venv's own, as plain paths: their .pth files (this checkout's editable install) stay unread."""
    import site
    import sysconfig

    mine = [*site.getsitepackages(), sysconfig.get_path("purelib"), sysconfig.get_path("platlib")]
    if site.ENABLE_USER_SITE:
        mine.append(site.getusersitepackages())
    probe = "import sysconfig; print(sysconfig.get_path('purelib'))"
    own = subprocess.run([str(env_dir / "bin" / "python"), "-c", probe], capture_output=True, text=True, check=True)
    folders = list(dict.fromkeys(p for p in mine if Path(p).is_dir()))
    (Path(own.stdout.strip()) / "_occvo_test_parent_site.pth").write_text("\n".join(folders) + "\n")


def _clean_env() -> dict:
    """No PYTHONPATH: the installed wheel must be what runs, not this checkout."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME")}


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_installed_wheel_serves_from_any_directory(venv, tmp_path):
    env, cwd = _clean_env(), tmp_path
    code = (
        f"import json, importlib; print(json.dumps({{p: importlib.import_module(p).__file__ for p in {PACKAGES!r}}}))"
    )
    where = subprocess.run(
        [str(venv / "python"), "-c", code], capture_output=True, text=True, env=env, cwd=cwd, check=True
    )
    for package, path in json.loads(where.stdout).items():
        assert Path(path).is_relative_to(venv.parent), f"{package} imported from {path}, not the installed wheel"
    # only the project's own import names: generic ones like `services` belong to nobody
    generic = "import importlib.util as u; print([n for n in ('services', 'schemas') if u.find_spec(n)])"
    found = subprocess.run([str(venv / "python"), "-c", generic], capture_output=True, text=True, env=env, cwd=cwd)
    assert found.stdout.strip() == "[]", found.stdout + found.stderr

    def occvo(*argv, timeout=900):
        proc = subprocess.run(
            [str(venv / "occvo"), *argv], check=False, capture_output=True, text=True, env=env, cwd=cwd, timeout=timeout
        )
        assert proc.returncode == 0, (argv, proc.stderr[-2000:])
        return proc

    assert occvo("--version").stdout.strip() == "occvo 0.1.0"
    run = json.loads(occvo("run", "--json", "--quiet").stdout)
    assert run["frames"] == 40 and run["success"] is True and run["compile_s"] > 0
    assert (cwd / "occvo-out" / "summary.json").is_file()

    ep = f"tcp/127.0.0.1:{_free_port()}"
    # the default identity: serve makes the logins in the user's config folder, the commands log in by themselves
    env = {k: v for k, v in env.items() if k not in ("OCCVO_LOGINS_DIR", "OCCVO_ZENOH_CONFIG")}
    env["XDG_CONFIG_HOME"] = str(tmp_path / "config")
    serve = subprocess.Popen(
        [str(venv / "occvo"), "serve", "--listen", ep, "--json", "--log-dir", str(tmp_path / "logs")],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
        cwd=cwd,
    )
    events: list[dict] = []

    def read() -> None:
        for line in serve.stdout:
            events.append(json.loads(line))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 600
        while not any(e["event"] == "ready" for e in events) and time.monotonic() < deadline and serve.poll() is None:
            time.sleep(0.5)
        assert any(e["event"] == "ready" for e in events), (
            events,
            serve.stderr.read() if serve.poll() is not None else "",
        )
        # the endpoint comes first, before the registration worker (announced after its kernels' warm-up)
        names = [(e["event"], e.get("role")) for e in events]
        assert events[0] == {"event": "listening", "endpoint": ep}
        assert names.index(("worker ready", "registration")) > 0
        connect = ["--connect", ep]
        replay = json.loads(occvo("replay", "synthetic:0", "--frames", "10", "--json", "--quiet", *connect).stdout)
        assert replay["poses"] == replay["frames"] == 10
        login = getpass.getuser()
        assert replay["stream"] == f"{login}.default"  # the login's prefix, added by the client
        own = tmp_path / "config" / "occvo" / "logins" / f"session-{login}.json5"
        assert own.stat().st_mode & 0o777 == 0o600
        poses = [json.loads(line) for line in occvo("poses", *connect).stdout.splitlines()]
        assert [p["seq"] for p in poses] == list(range(10))
        info = json.loads(occvo("map-info", "--json", *connect).stdout)
        assert info["last_seq"] == 9 and info["tile_count"] > 0
        ix, iy = info["tiles"][0]
        tile = json.loads(occvo("tile", str(ix), str(iy), "--json", *connect).stdout)
        assert tile["voxels"] > 0
    finally:
        serve.send_signal(signal.SIGINT)
        try:
            serve.wait(timeout=120)
        finally:
            if serve.poll() is None:
                serve.kill()
    reader.join(10)
    assert serve.returncode == 0, serve.stderr.read()[-2000:]
    assert events[-1] == {"event": "stopped", "exit_codes": {"inference": 0, "map": 0, "registration": 0}}
