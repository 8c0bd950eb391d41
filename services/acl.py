"""The authenticated default of `occvo serve` and `occvo up`: the router's config written from the logins
(services/logins.py) and the access control of services/defaults/acl_router.json5 (the worker rules of
deploy/acl/router.json5, and a copy of the client rules for each client login with its prefix), and the workers run
as their logins, knowing a client by its stream ids' prefix (`client_identity: "user"`)."""

from __future__ import annotations

import json
from pathlib import Path

from occvo_services import defaults, logins
from occvo_services.sessions import ZENOH_CONFIG_ENV

ROUTER_FILE = "router.json5"
WORKER_ARGS = ["--client-identity", "user"]  # a client is the login whose prefix its stream ids carry


def access_control(client_logins: list[str]) -> dict:
    """The router's access_control section: the worker rules, and the client rules once for each client login."""
    import json5

    template = json5.loads(defaults.path("acl_router.json5").read_text())
    rules, subjects, policies = list(template["rules"]), list(template["subjects"]), list(template["policies"])
    for login in client_logins:
        logins.check_login(login)
        for rule in template["client_rules"]:
            rules.append(json.loads(json.dumps(rule).replace("LOGIN", login)))
        subjects.append({"id": f"client_{login}", "usernames": [login]})
        policy = json.loads(json.dumps(template["client_policy"]).replace("LOGIN", login))
        policies.append({**policy, "subjects": [f"client_{login}"]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def write_router_config(folder: Path | None = None) -> Path:
    """The router's config for this start: the built-in router's (listen endpoint, message limit) with the logins'
    dictionary and the access control of today's client logins. The workers' logins are created if missing and, on a
    first start, the client login of the user running this."""
    import json5

    folder = folder or logins.logins_dir()
    logins.ensure(folder)
    config = json5.loads(defaults.path("router.json5").read_text())
    auth = config.setdefault("transport", {}).setdefault("auth", {})
    auth["usrpwd"] = {"dictionary_file": str((folder / logins.USERS_FILE).resolve())}
    config["access_control"] = access_control(logins.client_logins(folder))
    path = folder / ROUTER_FILE
    logins.write_private(path, json.dumps(config, indent=1) + "\n")
    return path.resolve()


def worker_env(role: str, folder: Path | None = None) -> dict[str, str]:
    """The environment that makes a worker log in as its role (a path: the password stays in the file)."""
    return {ZENOH_CONFIG_ENV: str(logins.session_file(role, folder).resolve())}


def authenticate(up_config, folder: Path | None = None) -> Path:
    """An `occvo up` deployment (services/supervisor.py's UpConfig) turned into the authenticated one: its router
    on the written config, each worker as its login; returns the client config the command itself may use."""
    folder = folder or logins.logins_dir()
    logins.ensure(folder)
    probe = probe_config(folder)  # before the router's config: it may add a login
    up_config.router.config = str(write_router_config(folder))
    for w in up_config.workers:
        w.env = {**w.env, **worker_env(w.role, folder)}
        w.args = [*w.args, *WORKER_ARGS]
    return probe


def probe_config(folder: Path | None = None) -> Path:
    """A client config `occvo serve` watches the workers' tokens with: the first client login's."""
    folder = folder or logins.logins_dir()
    own = logins.session_file(logins.default_login(), folder)
    if own.is_file():
        return own
    for login in logins.client_logins(folder):
        if logins.session_file(login, folder).is_file():
            return logins.session_file(login, folder)
    logins.add(logins.default_login(), folder)  # every client login was removed: the user running this gets one
    return own


class LoginsWatch:
    """Whether the logins changed (`occvo logins add/remove`) since the router's config was written: then it is
    written again and the caller restarts the router, which reads its dictionary and access control only at start.
    Looked at once a second at most."""

    def __init__(self, folder: Path | None = None, every_s: float = 1.0):
        self.folder = folder or logins.logins_dir()
        self.every_s, self._next = every_s, 0.0
        self._stamp = self._look()

    def _look(self):
        try:
            st = (self.folder / logins.USERS_FILE).stat()
        except OSError:
            return None
        return st.st_mtime_ns, st.st_size, st.st_ino

    def __call__(self) -> bool:
        import time

        now = time.monotonic()
        if now < self._next:
            return False
        self._next = now + self.every_s
        stamp = self._look()
        if stamp == self._stamp:
            return False
        self._stamp = stamp
        write_router_config(self.folder)
        return True
