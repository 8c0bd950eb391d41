"""Hostile-client step secrets (benchmarks/hostile_clients.py): `occvo serve` as a user starts it, on a PostgreSQL
store whose role needs a password, given in OCCVO_STORE_URL (the `?password=` form, which once reached logs and
events): the password in any `ps` line of serve's processes, any file of its log folder, serve's output, any event
a client got while the database was stopped; and written in `--store`, refused (exit 2, one line)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from _hostile_common import emit, goal
from _hostile_deploy import deploy

from occvo_services.client import OccVOClient
from occvo_services.local import REPO
from occvo_services.sessions import free_port
from occvo_services.store.pg_local import PgCluster
from occvo_services.store.url import STORE_URL_ENV

PASSWORD = "pw-Hostile@64"
SECRETS = (PASSWORD, "pw-Hostile%4064", "Hostile@64")


def _tree(pid: int) -> list[int]:
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


def _leaks(text: str) -> bool:
    return any(s in text for s in SECRETS)


def secrets(frames) -> None:
    cluster, tmp = PgCluster(), Path(tempfile.mkdtemp())
    cluster.add_password_user("occvo_hostile", PASSWORD)
    db = cluster.new_database().rsplit("/", 1)[1]
    url = f"postgresql://occvo_hostile@127.0.0.1:{cluster.port}/{db}?password={SECRETS[1]}"
    env = {**os.environ, "PYTHONPATH": str(REPO), STORE_URL_ENV: url}
    ep, logs = f"tcp/127.0.0.1:{free_port()}", tmp / "logs"
    serve = [sys.executable, "-m", "occvo_cli", "serve", "--listen", ep, "--json", "--log-dir", str(logs)]
    err = open(tmp / "serve.err", "w")  # noqa: SIM115 - closed after the process
    proc = subprocess.Popen(
        [*serve, *(["--anonymous"] if deploy().anonymous else [])],
        cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=err, text=True,
    )  # fmt: skip
    found, out, events = {}, [], []
    try:
        while not out or out[-1].get("event") != "ready":
            line = proc.stdout.readline()
            if not line:
                raise RuntimeError(f"serve ended: {(tmp / 'serve.err').read_text()[-2000:]}")
            out.append(json.loads(line))
        pids = _tree(proc.pid)
        ps = subprocess.run(["ps", "-ww", "-o", "pid=,args=", "-p", ",".join(map(str, pids))], capture_output=True)
        found["ps"] = _leaks(ps.stdout.decode()) or any(_leaks(Path(f"/proc/{p}/cmdline").read_text()) for p in pids)
        with OccVOClient(ep, "secret", resend_after=1.0) as c:
            c.reset()
            for f in frames[:3]:
                c.step(f)
            cluster.stop()
            try:
                c.publish(frames[3])
                with c._cv:
                    c._cv.wait_for(lambda: any(e.code == "store_unavailable" for e in c.errors), 60)
            finally:
                cluster.start()
            c.wait_pose(3, timeout=120)
            events = [e.message for e in c.errors]
    finally:
        proc.send_signal(signal.SIGINT)
        rest, _ = proc.communicate(timeout=120)
        err.close()
        cluster.close()
    found["events"] = any(_leaks(m) for m in events)
    found["logs"] = any(_leaks(f.read_text(errors="replace")) for f in [*logs.glob("*"), tmp / "serve.err"])
    found["output"] = _leaks(json.dumps(out) + rest)
    cli = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "serve", "--store", f"postgresql://occvo:{SECRETS[1]}@127.0.0.1:1/occvo"],
        cwd=REPO, env={k: v for k, v in env.items() if k != STORE_URL_ENV}, capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    lines = [x for x in cli.stderr.splitlines() if x.strip()]
    refused = cli.returncode == 2 and len(lines) == 1 and not _leaks(cli.stderr)
    emit("secrets", mode=deploy().name, processes=len(pids), events=len(events), log_files=len(list(logs.glob("*"))),
         password_in=found, store_flag_refused={"exit": cli.returncode, "lines": len(lines)})  # fmt: skip
    goal("the store's password in no ps line, log, output or event", not any(found.values()), **found)
    goal("a password written in --store is refused: exit 2, one line", refused, exit=cli.returncode)
    time.sleep(0.5)
