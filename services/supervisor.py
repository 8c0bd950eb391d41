"""`occvo up`: a router and the workers named in one json5 file, as child processes, kept running.

A child that exits with a nonzero code or is killed is started again after a backoff (0.5 s doubling to 30 s by
default, back to 0.5 s once it has stayed up 60 s). SIGINT/SIGTERM stop the workers first (each finishes its frame
in hand), then the router. Every event is a JSON line on stderr.

    {
      router: { config: "router.json5", listen: "tcp/127.0.0.1:7447" },   // paths relative to this file
      workers: [ { role: "registration", config: "registration_worker.json5", args: ["--store-path", "x.sqlite"], count: 1 } ],
      restart: { backoff_initial_s: 0.5, backoff_max_s: 30, reset_after_s: 60 },
    }
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from occvo_core.errors import ConfigError
from occvo_services import defaults
from occvo_services.runtime import log_event, structured_logger
from occvo_services.sessions import router_endpoint
from occvo_services.stop_signals import set_on_signal

REPO = Path(__file__).resolve().parents[1]
MODULES = {
    "inference": "occvo_services.inference_worker",
    "registration": "occvo_services.registration_worker",
    "map": "occvo_services.map_service",
    "ros2": "occvo_services.ros2",  # occvo's ROS 2 node (docs/ros2.md)
}


class RouterSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    config: str | None = None  # router json5; default deploy/router.json5
    listen: str | None = None  # replaces the file's listen endpoint
    connect: str | None = None  # what workers dial; default: the listen endpoint (0.0.0.0 -> 127.0.0.1)
    enabled: bool = True  # false: the router runs elsewhere (another host), only workers here


class WorkerSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    role: Literal["inference", "registration", "map", "ros2"]
    config: str | None = None
    args: list[str] = []
    count: int = Field(
        1, ge=1, le=64
    )  # replicas: registration ones share the streams (shards), others each handle every stream
    env: dict[str, str] = {}


class RestartSpec(BaseModel):
    model_config = ConfigDict(extra="forbid")
    backoff_initial_s: float = Field(0.5, gt=0)
    backoff_max_s: float = Field(30.0, gt=0)
    reset_after_s: float = Field(60.0, gt=0)


class UpConfig(BaseModel):
    model_config = ConfigDict(extra="forbid")
    router: RouterSpec = RouterSpec()
    workers: list[WorkerSpec]
    restart: RestartSpec = RestartSpec()
    stop_timeout_s: float = Field(60.0, gt=0)
    log_dir: str | None = None  # each child's stderr to <log_dir>/<name>.log (default: this stderr)
    # true: the built-in router without logins, clients who they say they are (`occvo up --anonymous`); false: with
    # no router config of its own, the router has logins and access control (services/acl.py)
    anonymous: bool = False

    @classmethod
    def load(cls, path: str | Path) -> UpConfig:
        """Read the json5 file; relative paths in it are relative to the file."""
        from occvo_core import config_file

        path = Path(path)
        cfg = config_file.validate(cls, config_file.read(path), path)
        base = path.resolve().parent

        def rel(p: str | None) -> str | None:
            return None if p is None else str((base / p) if not Path(p).is_absolute() else Path(p))

        cfg.router.config = rel(cfg.router.config)
        cfg.log_dir = rel(cfg.log_dir)
        for w in cfg.workers:
            w.config = rel(w.config)
        for f in (cfg.router.config, *(w.config for w in cfg.workers)):
            if f is not None and not Path(f).is_file():
                raise ConfigError(f"{path}: config file {f} not found")
        return cfg

    def endpoint(self) -> str:
        """The endpoint workers connect to."""
        if self.router.connect:
            return self.router.connect
        ep = self.router.listen or router_endpoint(self.router.config or defaults.path("router.json5"))
        return ep.replace("0.0.0.0", "127.0.0.1").replace("[::]", "[::1]")


class Backoff:
    """Restart delay of one child: initial, doubling to max; back to initial after the child stayed up reset_after."""

    def __init__(self, spec: RestartSpec):
        self.spec = spec
        self.delay = spec.backoff_initial_s

    def next(self, uptime_s: float) -> float:
        if uptime_s >= self.spec.reset_after_s:
            self.delay = self.spec.backoff_initial_s
        d = self.delay
        self.delay = min(self.delay * 2, self.spec.backoff_max_s)
        return d


class Child:
    def __init__(self, name: str, cmd: list[str], env: dict[str, str], spec: RestartSpec, role: str):
        self.name, self.cmd, self.env, self.role = name, cmd, env, role
        self.backoff = Backoff(spec)
        self.proc: subprocess.Popen | None = None
        self.started_at = 0.0
        self.restart_at: float | None = None  # when a crashed child starts again; inf: it exited cleanly, it stays
        self.restarts = 0

    def running(self, proc: subprocess.Popen) -> None:
        self.proc, self.started_at, self.restart_at = proc, time.monotonic(), None

    def restarting(self) -> None:
        self.restarts += 1

    def exited(self) -> None:
        """A clean exit is a decision (e.g. systemctl stop of one worker): not restarted."""
        self.proc, self.restart_at = None, float("inf")

    def crashed(self, now: float) -> float:
        """Its restart after the backoff its uptime earns; returns the delay."""
        delay = self.backoff.next(now - self.started_at)
        self.restart_at = now + delay
        return delay


def _die_with_parent() -> None:
    """In the child: SIGTERM when the supervisor dies, so no worker outlives a killed `occvo up` (Linux)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG


class Supervisor:
    def __init__(
        self, config: UpConfig, log: logging.Logger | None = None, role_names: bool = False, quiet: bool = False
    ):
        """role_names: a role with one replica is named after the role (`occvo serve`'s logs and exit codes);
        quiet: without a log_dir, the children's logs go nowhere instead of to this stderr."""
        self.quiet = quiet
        self.config = config
        self.log = log or structured_logger("occvo.up")
        self.endpoint = config.endpoint()
        self.stopping = threading.Event()
        self.reload = None  # a callable: true when the router's config changed (services/acl.py's LoginsWatch)
        env = dict(
            os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        )
        self.router: Child | None = None
        if config.router.enabled:
            cmd = [
                sys.executable,
                "-m",
                "occvo_services.router",
                "--config",
                config.router.config or str(defaults.path("router.json5")),
            ]
            if config.router.listen:
                cmd += ["--listen", config.router.listen]
            self.router = Child("router", cmd, env, config.restart, "router")
        self.workers: list[Child] = []
        for w in config.workers:
            for i in range(w.count):
                name = w.role if role_names and w.count == 1 else f"{w.role}-{i}"
                # registration replicas share the streams: replica i registers shard i of count
                shard = (
                    ["--shard", str(i), "--shards", str(w.count)] if w.role == "registration" and w.count > 1 else []
                )
                cmd = [
                    sys.executable,
                    "-m",
                    MODULES[w.role],
                    *(["--config", w.config] if w.config else []),
                    "--connect",
                    self.endpoint,
                    "--worker-id",
                    name,
                    *shard,
                    *w.args,
                ]
                self.workers.append(Child(name, cmd, {**env, **w.env}, config.restart, w.role))

    # -- children
    def _spawn(self, child: Child) -> None:
        err = subprocess.DEVNULL if self.quiet else None
        if self.config.log_dir:
            Path(self.config.log_dir).mkdir(parents=True, exist_ok=True)
            err = open(Path(self.config.log_dir) / f"{child.name}.log", "a")
        # own process group: a terminal's Ctrl-C reaches only the supervisor, which stops workers before the router
        proc = subprocess.Popen(
            child.cmd, cwd=REPO, env=child.env, stdout=err, stderr=err, process_group=0, preexec_fn=_die_with_parent
        )
        if err not in (None, subprocess.DEVNULL):
            err.close()
        child.running(proc)
        log_event(self.log, "started", name=child.name, role=child.role, pid=child.proc.pid, restarts=child.restarts)

    def _wait_router(self, timeout: float) -> None:
        """Until the router accepts TCP connections on its endpoint (tcp/tls), so workers do not start too early."""
        proto, _, addr = self.endpoint.partition("/")
        if proto not in ("tcp", "tls"):
            time.sleep(1.0)
            return
        host, _, port = addr.split("#")[0].rpartition(":")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline and not self.stopping.is_set():
            if self.router is not None and self.router.proc.poll() is not None:
                raise RuntimeError(f"router exited with code {self.router.proc.returncode} during start-up")
            try:
                with socket.create_connection((host.strip("[]"), int(port)), timeout=0.5):
                    return
            except OSError:
                time.sleep(0.1)
        if not self.stopping.is_set():
            raise TimeoutError(f"router not accepting connections on {self.endpoint} after {timeout} s")

    def start(self, timeout: float = 60.0) -> Supervisor:
        log_event(self.log, "up", endpoint=self.endpoint, workers=[c.name for c in self.workers], pid=os.getpid())
        if self.router is not None:
            self._spawn(self.router)
            self._wait_router(timeout)
        for child in self.workers:
            self._spawn(child)
        return self

    def pids(self) -> dict[str, int | None]:
        return {
            c.name: (c.proc.pid if c.proc and c.proc.poll() is None else None)
            for c in ([self.router] if self.router else []) + self.workers
        }

    def restart_router(self) -> None:
        """Stop the router and start it again at once, on its rewritten config; workers and clients reconnect."""
        if self.router is None or self.router.proc is None or self.stopping.is_set():
            return
        self._stop_group([self.router])
        self.router.restarting()
        self._spawn(self.router)
        log_event(self.log, "router restarted", reason="its config changed", pid=self.router.proc.pid)

    def poll(self) -> None:
        """Notice exited children and restart them when their backoff has passed."""
        if self.reload is not None and self.reload():
            self.restart_router()
        now = time.monotonic()
        for child in ([self.router] if self.router else []) + self.workers:
            if child.restart_at is not None:
                if now >= child.restart_at and not self.stopping.is_set():
                    child.restarting()
                    self._spawn(child)
                continue
            code = child.proc.poll() if child.proc else None
            if code is None:
                continue
            uptime = now - child.started_at
            if code == 0:  # a clean exit is a decision (e.g. systemctl stop of one worker): not restarted
                log_event(self.log, "exited", name=child.name, code=0, uptime_s=round(uptime, 3))
                child.exited()
                continue
            delay = child.crashed(now)
            how = f"signal {signal.Signals(-code).name}" if code < 0 else f"code {code}"
            log_event(
                self.log,
                "crashed",
                logging.WARNING,
                name=child.name,
                role=child.role,
                pid=child.proc.pid,
                code=code,
                how=how,
                uptime_s=round(uptime, 3),
                restart_in_s=delay,
            )

    def run(self, ready=None) -> int:
        """Start, supervise until SIGINT/SIGTERM, stop; returns 0 when every child stopped cleanly."""
        set_on_signal(self.stopping)
        try:
            self.start()
            if ready:
                ready(self)
            while not self.stopping.wait(0.1):
                self.poll()
        finally:
            codes = self.stop()
        # -SIGTERM: a child stopped by our SIGTERM before it set its handler (still importing): nothing was in hand
        return 0 if all(c in (0, None, -signal.SIGTERM) for c in codes.values()) else 1

    def stop(self) -> dict[str, int | None]:
        """SIGTERM the workers and wait for them (each finishes its frame in hand), then the router."""
        self.stopping.set()
        log_event(self.log, "stopping")
        codes = self._stop_group(self.workers)
        if self.router is not None:
            codes.update(self._stop_group([self.router]))
        log_event(self.log, "stopped", exit_codes=codes)
        return codes

    def _stop_group(self, children: list[Child]) -> dict[str, int | None]:
        live = [c for c in children if c.proc is not None and c.proc.poll() is None]
        for c in live:
            c.proc.send_signal(signal.SIGTERM)
        codes: dict[str, int | None] = {c.name: None for c in children}
        deadline = time.monotonic() + self.config.stop_timeout_s
        for c in live:
            try:
                codes[c.name] = c.proc.wait(timeout=max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                log_event(
                    self.log, "kill", logging.WARNING, name=c.name, pid=c.proc.pid, after_s=self.config.stop_timeout_s
                )
                c.proc.kill()
                codes[c.name] = c.proc.wait()
        return codes
