"""A throwaway PostgreSQL 15 server for the tests and benchmarks: a cluster made with initdb in a temporary folder,
listening on a free loopback port (its unix socket in that folder), fsync on as deployed, run by the `postgres` user
when run as root (the server refuses root; CI runs as root). Debian keeps the binaries off PATH:
/usr/lib/postgresql/15/bin."""

from __future__ import annotations

import os
import shutil
import subprocess
import tempfile
import time
import uuid
from pathlib import Path

BIN = Path("/usr/lib/postgresql/15/bin")


def missing() -> str | None:
    """Why no server can be started here, or None."""
    if not (BIN / "initdb").is_file() or not (BIN / "pg_ctl").is_file():
        return f"PostgreSQL 15 server binaries not found in {BIN} (apt-get install postgresql)"
    if os.geteuid() == 0 and shutil.which("runuser") is None:
        return "running as root needs runuser to start PostgreSQL as the postgres user"
    try:
        import psycopg  # noqa: F401
    except ModuleNotFoundError:
        return "the PostgreSQL driver is not installed (pip install -e '.[postgres]')"
    return None


class PgCluster:
    def __init__(self):
        from occvo_services.sessions import free_port

        self.root = Path(tempfile.mkdtemp(prefix="occvo-pg-"))
        self.data, self.log = self.root / "data", self.root / "server.log"
        self.port = free_port()
        if os.geteuid() == 0:
            shutil.chown(self.root, "postgres", "postgres")
        self._as_server([str(BIN / "initdb"), "-D", str(self.data), "-U", "postgres", "-A", "trust", "-N"])
        self.start()

    def _as_server(self, argv: list[str]) -> None:
        if os.geteuid() == 0:
            argv = ["runuser", "-u", "postgres", "--", *argv]
        out = subprocess.run(argv, capture_output=True, text=True, cwd=self.root)
        if out.returncode != 0:
            log = self.log.read_text()[-2000:] if self.log.is_file() else ""
            raise RuntimeError(f"{' '.join(argv)}: exit {out.returncode}\n{out.stdout}{out.stderr}{log}")

    def start(self) -> None:
        opts = f"-p {self.port} -k {self.root} -c listen_addresses=127.0.0.1 -c fsync=on -c max_connections=200"
        self._as_server([str(BIN / "pg_ctl"), "-D", str(self.data), "-l", str(self.log), "-o", opts, "-w", "start"])

    def stop(self, mode: str = "fast") -> None:
        self._as_server([str(BIN / "pg_ctl"), "-D", str(self.data), "-m", mode, "-w", "stop"])

    def url(self, dbname: str = "postgres", password: str | None = None) -> str:
        user = "postgres" if password is None else f"postgres:{password}"
        return f"postgresql://{user}@127.0.0.1:{self.port}/{dbname}"

    def add_password_user(self, user: str, password: str) -> None:
        """A role that must give its password over TCP (scram-sha-256); every other role stays trusted."""
        import psycopg
        from psycopg import sql

        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(sql.SQL("CREATE ROLE {} LOGIN SUPERUSER PASSWORD {}").format(sql.Identifier(user), password))
        hba = self.data / "pg_hba.conf"
        hba.write_text(f"host all {user} 127.0.0.1/32 scram-sha-256\n" + hba.read_text())  # first match wins
        self._as_server([str(BIN / "pg_ctl"), "-D", str(self.data), "-w", "reload"])
        deadline = time.monotonic() + 10.0
        while time.monotonic() < deadline:  # the server rereads its rules after the signal, not at once
            try:
                psycopg.connect(f"postgresql://{user}@127.0.0.1:{self.port}/postgres", password="").close()
            except psycopg.OperationalError:
                return
            time.sleep(0.05)
        raise RuntimeError(f"{hba}: the password rule for {user} was not taken up")

    def new_database(self) -> str:
        """A fresh, empty database of the cluster: its URL (one a test, so tests never see each other's rows)."""
        import psycopg

        name = f"occvo_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f'CREATE DATABASE "{name}"')
        return self.url(name)

    def close(self) -> None:
        try:
            self.stop("immediate")
        finally:
            shutil.rmtree(self.root, ignore_errors=True)
