"""A whole occvo service on one machine: a Zenoh router plus the three workers, as separate processes
(`occvo serve`, the end-to-end tests, benchmarks/pipeline.py) or as threads of this process (fast tests)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from occvo_schemas import keys
from occvo_services.os_tuning import short_gil_turns
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import free_port, open_router, open_session

REPO = Path(__file__).resolve().parents[1]
WORKERS = {
    "inference": "occvo_services.inference_worker",
    "registration": "occvo_services.registration_worker",
    "map": "occvo_services.map_service",
}


def wait_alive(session, roles, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    alive: set[str] = set()
    while time.monotonic() < deadline:
        alive = {
            str(r.ok.key_expr).split("/")[2]
            for r in session.liveliness().get(keys.alive("*", "*"), timeout=2.0)
            if r.ok
        }
        if set(roles) <= alive:
            return
        time.sleep(0.1)
    raise TimeoutError(f"workers {sorted(set(roles) - alive)} not alive after {timeout} s")


class LocalService:
    """Router in this process, workers as child processes (`python -m occvo_services.<module>`)."""

    def __init__(
        self,
        endpoint: str | None = None,
        router_config: str | None = None,
        worker_args: dict | None = None,
        common_args: list[str] | None = None,
        log_dir: str | Path | None = None,
        quiet: bool = False,
        registration_shards: int = 1,
        placement: str = "shards",
        pin: dict[str, str] | None = None,
        worker_env: dict[str, dict[str, str]] | None = None,
    ):
        self.endpoint = endpoint or f"tcp/127.0.0.1:{free_port()}"
        self.router_config = router_config
        self.worker_args = worker_args or {}
        self.common_args = common_args or []
        self.log_dir = Path(log_dir) if log_dir else None
        self.quiet = quiet
        self.registration_shards = registration_shards  # registration workers sharing the streams
        self.placement = placement  # "members": they share them by rendezvous hashing under store leases
        self.pin = pin or {}  # worker name -> the cores it may run on (taskset -c)
        self.worker_env = worker_env or {}  # role -> extra environment (OCCVO_ZENOH_CONFIG: its ACL login)
        self.procs: dict[str, subprocess.Popen] = {}  # by role, or registration-<shard> when sharded
        self.router = None

    def start(self, timeout: float = 180.0) -> LocalService:
        """Until every worker is alive: a registration worker on a fresh install first compiles its kernels (36 s
        alone on this 2-core machine, 42 s for two shards side by side; occvo_core/warm_up.py)."""
        self.router = open_router(self.endpoint, self.router_config)
        env = dict(
            os.environ, PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep)
        )
        try:
            n = self.registration_shards
            for name, role, shard in [("inference", "inference", []), ("map", "map", [])] + (
                [("registration", "registration", self._placement(0, 1))]
                if n == 1
                else [(f"registration-{i}", "registration", self._placement(i, n)) for i in range(n)]
            ):
                cmd = [
                    *(["taskset", "-c", self.pin[name]] if name in self.pin else []),
                    sys.executable,
                    "-m",
                    WORKERS[role],
                    "--connect",
                    self.endpoint,
                    "--worker-id",
                    f"{name}-{os.getpid()}",
                    *shard,
                    *self.common_args,
                    *self.worker_args.get(role, []),
                ]
                err = (
                    open(self.log_dir / f"{name}.log", "w")
                    if self.log_dir
                    else (subprocess.DEVNULL if self.quiet else None)
                )
                role_env = {**env, **self.worker_env.get(role, {})}
                self.procs[name] = subprocess.Popen(cmd, cwd=REPO, env=role_env, stderr=err, stdout=err)
            # the shipped ACL gives its clients no liveliness replies (zenoh 1.10): then the router itself is asked
            probe = self.router if self.router_config else open_session(self.endpoint)
            try:
                deadline = time.monotonic() + timeout
                while True:
                    dead = {r: p.returncode for r, p in self.procs.items() if p.poll() is not None}
                    if dead:
                        raise RuntimeError(f"workers exited during start-up: {dead}")
                    try:
                        wait_alive(probe, WORKERS, timeout=1.0)
                        shards = [r for r in probe.liveliness().get(keys.registration_shard(), timeout=2.0) if r.ok]
                        if len(shards) < self.registration_shards:
                            raise TimeoutError(f"{len(shards)} of {self.registration_shards} registration shards alive")
                        break
                    except TimeoutError:
                        if time.monotonic() > deadline:
                            raise
            finally:
                if probe is not self.router:
                    probe.close()
        except BaseException:
            self.stop()
            raise
        return self

    def _placement(self, i: int, n: int) -> list[str]:
        if self.placement == "members":
            return ["--placement", "members"]
        return ["--shard", str(i), "--shards", str(n)]

    def stop(self, timeout: float = 30.0) -> dict[str, int | None]:
        """Stop the workers, then the router; returns the workers' exit codes."""
        codes = self.stop_workers(timeout)
        if self.router is not None:
            self.router.close()
            self.router = None
        return codes

    def stop_workers(self, timeout: float = 30.0) -> dict[str, int | None]:
        """SIGTERM every worker (each finishes its frame in hand), wait, kill stragglers; returns exit codes."""
        for p in self.procs.values():
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        codes = {}
        for role, p in self.procs.items():
            try:
                codes[role] = p.wait(timeout=timeout)
            except subprocess.TimeoutExpired:
                p.kill()
                codes[role] = p.wait()
        self.procs.clear()
        return codes

    def __enter__(self) -> LocalService:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()


class InProcessService:
    """Router and the three workers as threads of this process: same code and real Zenoh sessions, faster start.
    While it runs, the process takes the workers' short interpreter-lock turns (os_tuning.short_gil_turns)."""

    def __init__(self, endpoint: str | None = None, **config):
        self.endpoint = endpoint or f"tcp/127.0.0.1:{free_port()}"
        self.config = config
        self.workers = []
        self.router = None
        self._switch_interval = None  # the process's own, given back at stop()

    def start(self, timeout: float = 30.0) -> InProcessService:
        from occvo_services.inference_worker import InferenceWorker
        from occvo_services.map_service import MapService
        from occvo_services.registration_worker import RegistrationWorker

        self._switch_interval = short_gil_turns()
        self.router = open_router(self.endpoint)
        cfg = {"log_level": "WARNING", **self.config, "connect": self.endpoint}
        try:
            for cls in (MapService, RegistrationWorker, InferenceWorker):
                self.workers.append(cls(WorkerConfig(**{**cfg, "worker_id": f"{cls.role}-{id(self):x}"})).start())
            probe = open_session(self.endpoint)
            try:
                wait_alive(probe, WORKERS, timeout)
            finally:
                probe.close()
        except BaseException:
            self.stop()
            raise
        return self

    def worker(self, role: str):
        return next(w for w in self.workers if w.role == role)

    def stop(self) -> None:
        for w in reversed(self.workers):
            w.stop()
        self.workers.clear()
        if self.router is not None:
            self.router.close()
            self.router = None
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None

    def __enter__(self) -> InProcessService:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()
