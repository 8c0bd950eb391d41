"""Hostile-client steps of slot grabbers by identity (benchmarks/hostile_clients.py): a service with client_identity
"user" on a plain router, and the service behind the shipped ACL with five camera logins."""

from __future__ import annotations

import copy
import json
import os
import tempfile
import time
from pathlib import Path

import json5
from _hostile_abuse import grabber
from _hostile_common import run_replay

from occvo_schemas import keys
from occvo_schemas.codec import decode
from occvo_schemas.models import WorkerHealth
from occvo_services.local import REPO, LocalService
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import ZENOH_CONFIG_ENV

ACL = REPO / "deploy" / "acl"
HOSTILE = ["camera", "camera2", "camera3", "camera4"]  # the shipped file's two camera users and two more
LEGIT = "camera5"


def acl_logins(folder: Path, cameras: list[str]) -> tuple[Path, dict[str, Path]]:
    """The shipped ACL on loopback with a users file, a subject and rules for each camera user it lacks (copies of
    user camera's with the user's prefix, as router.json5 says), and each user's session config: (router config,
    {user: session config}). Passwords are pw-<user>."""
    cfg = json5.loads((ACL / "router.json5").read_text())
    cfg["listen"]["endpoints"] = ["tcp/127.0.0.1:7447"]  # LocalService puts its free port there
    cfg["transport"]["auth"]["usrpwd"]["dictionary_file"] = str(folder / "users.txt")
    ac = cfg["access_control"]
    rules = {r["id"]: r for r in ac["rules"]}
    known = {s["id"] for s in ac["subjects"]}
    camera_policy = next(p for p in ac["policies"] if p["subjects"] == ["camera"])
    for user in [c for c in cameras if c not in known]:
        for suffix in ("frames", "follow"):
            rule = copy.deepcopy(rules[f"camera_{suffix}"])
            rule["id"] = f"{user}_{suffix}"
            rule["key_exprs"] = [k.replace("occvo/camera.$*", f"occvo/{user}.$*") for k in rule["key_exprs"]]
            ac["rules"].append(rule)
        ac["subjects"].append({"id": user, "usernames": [user]})
        own = [f"{user}_frames", f"{user}_follow"]
        shared = [r for r in camera_policy["rules"] if not r.startswith("camera_")]  # receiving outputs, answers
        ac["policies"].append({"rules": own + shared, "subjects": [user]})
        for p in ac["policies"]:
            if "see_declarations" in p["rules"]:
                p["subjects"].append(user)
    users = sorted({s["usernames"][0] for s in ac["subjects"]})
    (folder / "users.txt").write_text("".join(f"{u}:pw-{u}\n" for u in users))
    (folder / "router.json5").write_text(json.dumps(cfg))
    sessions = {}
    for u in users:
        shipped = ACL / f"session-{u}.json5"
        text = shipped.read_text() if shipped.exists() else (ACL / "session-camera.json5").read_text()
        sessions[u] = folder / f"session-{u}.json5"
        sessions[u].write_text(text.replace('user: "camera"', f'user: "{u}"').replace("CHANGE-ME", f"pw-{u}"))
    return folder / "router.json5", sessions


def grabber_user(frames, worker_args: dict) -> None:
    """The ACL's identity rule without its logins: client_identity "user" on a plain router, 4 users x 16 streams."""
    svc = LocalService(quiet=True, common_args=["--client-identity", "user"], worker_args=worker_args).start()
    try:
        solo_s, _ = run_replay(svc.endpoint, "viewer.solo", frames)
        users = [[f"camera{u}.s{i}" for i in range(16)] for u in range(1, 5)]
        grabber(svc.endpoint, frames, solo_s, users, "viewer.car", "client_identity user, 4 users x 16 streams")
    finally:
        svc.stop()


def grabber_acl(frames, worker_args, reg_config: str) -> None:
    """Behind the shipped ACL (client_identity "user"), each worker and client its own login: 4 camera logins each
    holding max_streams_per_client streams (a frame on each every 2 s) beside a fifth login's replay.
    worker_args(store): the workers' arguments; the store is this step's own (the user step's stream ids are these)."""
    folder = Path(tempfile.mkdtemp())
    router, sessions = acl_logins(folder, [*HOSTILE, LEGIT])
    env = {role: {ZENOH_CONFIG_ENV: str(sessions[role])} for role in ("inference", "registration", "map")}
    svc = LocalService(
        quiet=True,
        router_config=str(router),
        common_args=["--client-identity", "user"],
        worker_args=worker_args(["--store-path", str(folder / "occvo.sqlite")]),
        worker_env=env,
    ).start()
    config = WorkerConfig.load(reg_config)

    def health(role: str) -> WorkerHealth:  # asked through the router's own session (the logins may not read stats)
        replies = [r.ok for r in svc.router.get(keys.stats(f"{role}-{os.getpid()}"), timeout=10.0) if r.ok]
        return decode(replies[0].payload.to_bytes(), WorkerHealth)

    def served() -> dict:
        out = {}
        for role in ("inference", "registration"):
            h = health(role)
            held = {u: sum(s.split(".")[0] == u for s in h.streams) for u in [*HOSTILE, LEGIT]}
            out[role] = {"streams_by_login": held, "streams_refused": h.counters.get("streams_refused", 0)}
        return out

    try:
        solo_s, _ = run_replay(svc.endpoint, f"{LEGIT}.solo", frames, sessions[LEGIT])
        deadline = time.monotonic() + config.idle_stream_s + 60  # the solo stream retired: the logins fill max_streams
        while any(f"{LEGIT}.solo" in health(r).streams for r in ("inference", "registration")):
            assert time.monotonic() < deadline, "the solo replay's stream was not retired"
            time.sleep(1.0)
        groups = [[f"{u}.s{i}" for i in range(config.max_streams_per_client)] for u in HOSTILE]
        logins = ([sessions[u] for u in HOSTILE], sessions[LEGIT], served)
        label = f"ACL, 4 logins x {config.max_streams_per_client} streams (max_streams {config.max_streams})"
        grabber(svc.endpoint, frames, solo_s, groups, f"{LEGIT}.car", f"{label}, the replay a fifth login", logins)
    finally:
        svc.stop()
