"""deploy/: every config file loads, and a router opened from each one works on a free loopback port: the loopback
default, a two-router mesh, TLS with mutual authentication (certificates made by openssl in tmp_path), and
access control (allowed flows pass, denied ones do not). Also the systemd units, compose.yaml and the Dockerfile
refer to files and modules that exist."""

from __future__ import annotations

import importlib.util
import json
import re
import shutil
import subprocess
import time
import warnings
from pathlib import Path

import pytest
import zenoh
from mesh_certs import make_certificates, shipped

from occvo_services.router import router_config
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import free_port, zenoh_config

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
WORKER_FILES = sorted(p for p in DEPLOY.rglob("*.json5") if "worker" in p.name or p.name == "map_service.json5")
ZENOH_FILES = sorted(p for p in DEPLOY.rglob("*.json5") if p.name.startswith(("router", "client", "session-")))
WORKER_MODULES = {"occvo_services.inference_worker", "occvo_services.registration_worker", "occvo_services.map_service"}


def _wait(pred, timeout=5.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if pred():
            return True
        time.sleep(0.05)
    return pred()


def _client(endpoint: str, base: Path | None = None, **inserts) -> zenoh.Session:
    c = zenoh_config("client", connect=endpoint, base=base)
    for key, value in inserts.items():
        c.insert_json5(key.replace("__", "/"), json.dumps(value))
    return zenoh.open(c)


def _delivered(pub: zenoh.Session, sub: zenoh.Session, key: str, timeout: float = 3.0) -> bool:
    """Does a put on `key` from `pub` reach a subscriber on `sub`? Puts repeatedly until it does or time is up."""
    got = []
    s = sub.declare_subscriber(key, lambda sample: got.append(sample.payload.to_bytes()))
    try:
        deadline = time.monotonic() + timeout
        while not got and time.monotonic() < deadline:
            pub.put(key, b"x")
            time.sleep(0.1)
        return bool(got)
    finally:
        s.undeclare()


def _answers(session: zenoh.Session, selector: str, timeout: float = 3.0) -> list[bytes]:
    """Replies to a get, asked again until some come or time is up (a new queryable takes a moment to propagate)."""
    deadline = time.monotonic() + timeout
    while True:
        got = [r.ok.payload.to_bytes() for r in session.get(selector, timeout=1.0) if r.ok]
        if got or time.monotonic() > deadline:
            return got
        time.sleep(0.1)


# ---------------------------------------------------------------- every file loads


def test_zenoh_config_files_load():
    assert {p.relative_to(DEPLOY).as_posix() for p in ZENOH_FILES} >= {
        "router.json5",
        "multihost/router-a.json5",
        "multihost/router-b.json5",
        "tls/router.json5",
        "tls/client.json5",
        "acl/router.json5",
        "acl/session-viewer.json5",
    }
    for path in ZENOH_FILES:
        c = zenoh.Config.from_file(str(path))
        mode = json.loads(c.get_json("mode"))
        assert mode == ("router" if path.name.startswith("router") else "client"), path
    acl = zenoh.Config.from_file(str(DEPLOY / "acl/router.json5"))
    assert json.loads(acl.get_json("access_control/enabled")) is True
    tls = json.loads(zenoh.Config.from_file(str(DEPLOY / "tls/router.json5")).get_json("transport/link/tls"))
    assert tls["enable_mtls"] is True and tls["listen_certificate"].endswith("router.pem")


def test_worker_config_files_load():
    assert len(WORKER_FILES) >= 7
    for path in WORKER_FILES:
        cfg = WorkerConfig.load(path)
        assert re.match(r"^(tcp|tls)/[\w.\-]+:\d+$", cfg.connect), (path, cfg.connect)


def test_client_sessions_start_from_occvo_zenoh_config(monkeypatch, tmp_path):
    """Workers and clients take TLS certificates or ACL credentials from the file named by $OCCVO_ZENOH_CONFIG;
    their own endpoint wins, the reconnect retry is added unless the file sets one."""
    from occvo_core.errors import ConfigError
    from occvo_services.sessions import ZENOH_CONFIG_ENV

    monkeypatch.setenv(ZENOH_CONFIG_ENV, str(DEPLOY / "tls/client.json5"))
    c = zenoh_config("client", connect="tls/localhost:1")
    assert json.loads(c.get_json("transport/link/tls/root_ca_certificate")) == "/etc/occvo/tls/ca.pem"
    assert json.loads(c.get_json("connect/endpoints")) == ["tls/localhost:1"]
    assert json.loads(c.get_json("connect/retry"))["period_max_ms"] == 500
    assert (
        json.loads(zenoh_config("router", listen="tcp/127.0.0.1:1").get_json("transport/link/tls/root_ca_certificate"))
        is None
    )
    (tmp_path / "bad.json5").write_text("{ transport: { nonsense: 1 } }")
    monkeypatch.setenv(ZENOH_CONFIG_ENV, str(tmp_path / "bad.json5"))
    with pytest.raises(ConfigError, match="bad.json5"):
        zenoh_config("client", connect="tcp/127.0.0.1:1")


# ---------------------------------------------------------------- routers from the files work


def test_loopback_router_file_works():
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(router_config(DEPLOY / "router.json5", listen=[ep])):
        a, b = _client(ep), _client(ep)
        try:
            assert _delivered(a, b, "occvo/t/pose")
        finally:
            a.close()
            b.close()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not found on PATH: cannot make TLS certificates")
def test_router_mesh_files_work(tmp_path):
    """Router B (connect to A, retrying) starts first; clients on A and B exchange data through the mesh (mutual TLS:
    the certificates of docs/service.md's recipe; tests/system/test_mesh_tls.py runs the workers through it)."""
    make_certificates(tmp_path)
    pa, pb = free_port(), free_port()
    ep_a, ep_b = f"tls/localhost:{pa}", f"tls/localhost:{pb}"
    b = zenoh.open(router_config(shipped("router-b.json5", tmp_path, tmp_path), listen=[f"tls/127.0.0.1:{pb}"],
                                 connect=[ep_a]))  # fmt: skip
    a = zenoh.open(router_config(shipped("router-a.json5", tmp_path, tmp_path), listen=[f"tls/127.0.0.1:{pa}"]))

    def login(ep, role):
        return zenoh.open(zenoh_config("client", connect=ep, base=shipped(f"session-{role}.json5", tmp_path, tmp_path)))

    inference_b, registration_a, map_b, camera_a = login(ep_b, "inference"), login(ep_a, "registration"), None, None
    try:
        map_b, camera_a = login(ep_b, "map"), login(ep_a, "camera")
        assert _delivered(inference_b, registration_a, "occvo/camera.mesh/occupancy", timeout=10)  # B retries <= 4 s
        assert _delivered(registration_a, map_b, "occvo/camera.mesh/map/updates")
        key = "occvo/camera.mesh/map/info"
        q = map_b.declare_queryable(key, lambda query: query.reply(key, b"info"))
        assert _answers(camera_a, key) == [b"info"]
        q.undeclare()
        with pytest.raises(zenoh.ZError):  # plain tcp: refused
            zenoh.open(zenoh_config("client", connect=f"tcp/127.0.0.1:{pa}")).close()
    finally:
        for s in (camera_a, map_b, registration_a, inference_b, a, b):
            if s is not None:
                s.close()


def _openssl(*args, cwd):
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=30)


def make_certs(d: Path) -> None:
    """The commands of deploy/tls/README.md, with localhost names."""
    _openssl(
        "req",
        "-x509",
        "-newkey",
        "rsa:2048",
        "-nodes",
        "-days",
        "30",
        "-keyout",
        "ca.key",
        "-out",
        "ca.pem",
        "-subj",
        "/CN=occvo-ca",
        cwd=d,
    )
    for name, san, usage in (
        ("router", "DNS:localhost,IP:127.0.0.1", "serverAuth,clientAuth"),
        ("registration", "DNS:occvo-registration", "clientAuth"),  # roles by common name (the router's ACL)
        ("viewer", "DNS:occvo-viewer", "clientAuth"),
        ("client", "DNS:occvo-client", "clientAuth"),  # a certificate of no role
    ):
        _openssl(
            "req",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            f"{name}.key",
            "-out",
            f"{name}.csr",
            "-subj",
            f"/CN=occvo-{name}",
            cwd=d,
        )
        (d / f"{name}.ext").write_text(f"subjectAltName={san}\nextendedKeyUsage={usage}\n")
        _openssl(
            "x509",
            "-req",
            "-in",
            f"{name}.csr",
            "-CA",
            "ca.pem",
            "-CAkey",
            "ca.key",
            "-CAcreateserial",
            "-days",
            "30",
            "-out",
            f"{name}.pem",
            "-extfile",
            f"{name}.ext",
            cwd=d,
        )


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not found on PATH: cannot make TLS certificates")
def test_tls_router_and_client_files_work(tmp_path):
    make_certs(tmp_path)
    port = free_port()
    ep = f"tls/localhost:{port}"
    rc = router_config(DEPLOY / "tls/router.json5", listen=[f"tls/127.0.0.1:{port}"])
    rc.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(tmp_path / "ca.pem")))
    rc.insert_json5("transport/link/tls/listen_certificate", json.dumps(str(tmp_path / "router.pem")))
    rc.insert_json5("transport/link/tls/listen_private_key", json.dumps(str(tmp_path / "router.key")))

    def tls_paths(name):
        return {
            "transport__link__tls__root_ca_certificate": str(tmp_path / "ca.pem"),
            "transport__link__tls__connect_certificate": str(tmp_path / f"{name}.pem"),
            "transport__link__tls__connect_private_key": str(tmp_path / f"{name}.key"),
        }

    with zenoh.open(rc):
        # the access control shipped with the TLS config: the registration role's pose reaches a viewer; a
        # certificate of no role publishes nothing
        a = _client(ep, DEPLOY / "tls/client.json5", **tls_paths("registration"))
        b = _client(ep, DEPLOY / "tls/client.json5", **tls_paths("viewer"))
        c = _client(ep, DEPLOY / "tls/client.json5", **tls_paths("client"))
        try:
            assert _delivered(a, b, "occvo/tls/pose")
            assert not _delivered(c, b, "occvo/tls2/pose")
        finally:
            a.close()
            b.close()
            c.close()
        # mutual TLS: without a client certificate, or over plain tcp, the router refuses the session
        no_cert = {
            "transport__link__tls__root_ca_certificate": str(tmp_path / "ca.pem"),
            "transport__link__tls__enable_mtls": False,
            "transport__link__tls__connect_certificate": None,
            "transport__link__tls__connect_private_key": None,
        }
        with pytest.raises(zenoh.ZError):
            _client(ep, DEPLOY / "tls/client.json5", **no_cert).close()
        with pytest.raises(zenoh.ZError):
            _client(f"tcp/127.0.0.1:{port}").close()


def test_access_control_router_file(tmp_path):
    users = ["inference", "registration", "map", "camera", "viewer"]
    (tmp_path / "users.txt").write_text("".join(f"{u}:pw-{u}\n" for u in users))
    ep = f"tcp/127.0.0.1:{free_port()}"
    rc = router_config(DEPLOY / "acl/router.json5", listen=[ep])
    rc.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(tmp_path / "users.txt")))
    with zenoh.open(rc):
        with pytest.raises(zenoh.ZError):  # a wrong password gets no session
            _client(ep, DEPLOY / "acl/session-viewer.json5", transport__auth__usrpwd__password="wrong").close()
        s = {
            u: _client(ep, DEPLOY / f"acl/session-{u}.json5", transport__auth__usrpwd__password=f"pw-{u}")
            for u in users
        }
        try:
            # the pipeline's own flows pass
            assert _delivered(s["camera"], s["inference"], "occvo/camera.car/camera")  # under its own prefix
            assert _delivered(s["inference"], s["registration"], "occvo/car/occupancy")
            assert _delivered(s["registration"], s["map"], "occvo/car/map/updates")
            assert _delivered(s["registration"], s["viewer"], "occvo/car/pose")
            assert _delivered(s["registration"], s["camera"], "occvo/camera.car/pose")
            # a worker may put only on its outputs, a viewer may not publish at all
            assert not _delivered(s["map"], s["viewer"], "occvo/car/pose", timeout=1)
            assert not _delivered(s["inference"], s["camera"], "occvo/car/pose", timeout=1)
            assert not _delivered(s["viewer"], s["inference"], "occvo/car/camera", timeout=1)
            assert not _delivered(s["camera"], s["registration"], "occvo/car/occupancy", timeout=1)
            # a viewer subscribes to poses only
            assert not _delivered(s["inference"], s["viewer"], "occvo/car/occupancy", timeout=1)
            # the viewer gets tiles from the map service, but cannot ask the workers' stats
            tile = s["map"].declare_queryable("occvo/car/map/tile/*/*", lambda q: q.reply(str(q.key_expr), b"tile"))
            stats = s["map"].declare_queryable(
                "occvo/@workers/map-1/stats", lambda q: q.reply(str(q.key_expr), b"stats")
            )
            assert _answers(s["viewer"], "occvo/car/map/tile/1/2") == [b"tile"]
            assert _answers(s["inference"], "occvo/@workers/map-1/stats") == [b"stats"]
            assert not _answers(s["viewer"], "occvo/@workers/*/stats", timeout=1)
            # and may not answer tile queries itself
            fake = s["viewer"].declare_queryable("occvo/evil/map/tile/*/*", lambda q: q.reply(str(q.key_expr), b"fake"))
            assert not _answers(s["camera"], "occvo/evil/map/tile/0/0", timeout=1)
            for e in (tile, stats, fake):
                e.undeclare()
        finally:
            for sess in s.values():
                sess.close()


# ---------------------------------------------------------------- systemd, compose, Dockerfile

UNITS = ["occvo-router", "occvo-inference", "occvo-registration", "occvo-map"]


def _unit(name: str) -> dict[str, dict[str, list[str]]]:
    out: dict[str, dict[str, list[str]]] = {}
    section = None
    for line in (DEPLOY / "systemd" / f"{name}.service").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith(("#", ";")):
            continue
        if line.startswith("["):
            section = out.setdefault(line.strip("[]"), {})
            continue
        k, v = line.split("=", 1)
        section.setdefault(k.strip(), []).append(v.strip())
    return out


def _module_exists(module: str) -> bool:
    return importlib.util.find_spec(module) is not None


def test_systemd_units_parse_and_name_real_modules():
    for name in UNITS:
        u = _unit(name)
        svc = u["Service"]
        assert svc["Restart"] == ["on-failure"] and float(svc["RestartSec"][0].rstrip("s")) > 0
        assert svc["User"] == ["occvo"] and svc["EnvironmentFile"][0].lstrip("-") == "/etc/occvo/occvo.env"
        module = re.search(r"-m (occvo_services\.\w+)", svc["ExecStart"][0]).group(1)
        assert _module_exists(module), module
        config = re.search(r"--config (\S+)", svc["ExecStart"][0]).group(1)
        assert config.startswith("/etc/occvo/") and (DEPLOY / Path(config).name).is_file(), config
        if name != "occvo-router":
            assert (
                "occvo-router.service" in u["Unit"]["Requires"][0] and "occvo-router.service" in u["Unit"]["After"][0]
            )
            assert module in WORKER_MODULES


@pytest.mark.skipif(
    shutil.which("systemd-analyze") is None, reason="systemd-analyze not found; the units were only parsed"
)
def test_systemd_units_verify(tmp_path):
    """systemd-analyze verify checks the unit syntax and that ExecStart's binary exists; the python named there
    (/opt/occvo/venv/bin/python) is absent on this machine, so the units are verified with it pointed at this one."""
    import sys

    for name in UNITS:
        text = (
            (DEPLOY / "systemd" / f"{name}.service").read_text().replace("/opt/occvo/venv/bin/python", sys.executable)
        )
        (tmp_path / f"{name}.service").write_text(text)
    r = subprocess.run(
        ["systemd-analyze", "verify", *[str(tmp_path / f"{n}.service") for n in UNITS]],
        capture_output=True,
        text=True,
        timeout=60,
    )
    # verify exits 0 on unknown keys and bad values but prints them: any line about our units is a failure
    ours = [line for line in (r.stdout + r.stderr).splitlines() if "occvo-" in line]
    assert r.returncode == 0 and not ours, r.stdout + r.stderr


def test_compose_and_dockerfile_refer_to_real_files():
    yaml = pytest.importorskip("yaml", reason="PyYAML not installed: compose.yaml not checked")
    compose = yaml.safe_load((DEPLOY / "compose.yaml").read_text())
    services = compose["services"]
    assert set(services) == {"router", "inference", "registration", "map", "postgres"}
    assert (DEPLOY / Path(services["router"]["build"]["dockerfile"]).name).is_file()
    assert services["postgres"]["image"].startswith("postgres:") and "occvo-pg" in compose["volumes"]
    for name, svc in services.items():
        if name == "postgres":
            continue
        cmd = svc["command"]
        module = cmd[cmd.index("-m") + 1]
        assert _module_exists(module), (name, module)
        for vol in svc.get("volumes", []):
            src = vol.split(":")[0]
            if src.startswith("./"):
                assert (DEPLOY / src).exists(), (name, src)
            else:
                assert src in compose["volumes"], (name, src)
        if name != "router":
            assert "router" in svc["depends_on"] and module in WORKER_MODULES
            assert cmd[cmd.index("--connect") + 1] == "tcp/router:7447"
    docker = (DEPLOY / "Dockerfile").read_text()
    for src in re.findall(r"^COPY (?:--\S+ )?(\S+) ", docker, re.M):
        assert (REPO / src).exists(), src


def _dockerfile_copies() -> list[tuple[list[str], str]]:
    """The Dockerfile's COPY instructions from the build context (the repository root): (sources, destination)."""
    docker = (DEPLOY / "Dockerfile").read_text()
    copies = []
    for line in re.findall(r"^COPY (.+)$", docker, re.M):
        words = line.split()
        if any(w.startswith("--from") for w in words):
            continue  # from another build stage, not from the checkout
        *sources, dest = [w for w in words if not w.startswith("--")]
        copies.append((sources, dest))
    return copies


@pytest.mark.packaging
@pytest.mark.slow
def test_the_dockerfile_installs_from_exactly_the_files_it_copies(tmp_path):
    """What `docker build` does, without docker: the files the Dockerfile copies, laid out as it lays them out in its
    WORKDIR, and nothing else, build and install (pip, no dependencies: those are the image's earlier layers), and
    the installed `occvo --version` runs."""
    from test_packaging import _clean_env, install_in_fresh_venv

    workdir = tmp_path / "workdir"
    workdir.mkdir()
    for sources, dest in _dockerfile_copies():
        for name in sources:
            # COPY of a folder copies its contents; several sources (or a destination ending in /) go into the folder
            target = workdir / dest / name if len(sources) > 1 or dest.endswith("/") else workdir / dest
            if (REPO / name).is_dir():
                shutil.copytree(REPO / name, target, dirs_exist_ok=True)
            else:
                target.parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(REPO / name, target)
    bin_dir = install_in_fresh_venv(workdir, tmp_path)
    proc = subprocess.run(
        [str(bin_dir / "occvo"), "--version"], capture_output=True, text=True, env=_clean_env(), cwd=tmp_path
    )
    assert proc.returncode == 0 and proc.stdout.startswith("occvo "), proc.stderr[-2000:]


def test_every_flag_in_units_and_compose_is_accepted(capsys, monkeypatch):
    """Each --flag the units and compose.yaml pass exists in that module's argument parser (its --help, run in-process)."""
    import runpy
    import sys

    yaml = pytest.importorskip("yaml", reason="PyYAML not installed: compose.yaml not checked")
    commands = [_unit(n)["Service"]["ExecStart"][0].split()[1:] for n in UNITS]
    services = yaml.safe_load((DEPLOY / "compose.yaml").read_text())["services"].values()
    commands += [s["command"][1:] for s in services if "command" in s]
    flags: dict[str, set[str]] = {}
    for cmd in commands:
        flags.setdefault(cmd[cmd.index("-m") + 1], set()).update(a for a in cmd if a.startswith("--"))
    assert set(flags) == WORKER_MODULES | {"occvo_services.router"}
    for module, wanted in flags.items():
        monkeypatch.setattr(sys, "argv", [module, "--help"])
        with pytest.raises(SystemExit) as exit_, warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # runpy: the module is already imported; harmless here
            runpy.run_module(module, run_name="__main__", alter_sys=False)
        out = capsys.readouterr().out
        assert exit_.value.code == 0 and "usage:" in out, module
        assert not {f for f in wanted if f not in out}, (module, wanted)
