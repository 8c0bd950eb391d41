"""The deployment the hostile steps run against (benchmarks/hostile_clients.py): `occvo serve`'s default, logins and
access control (services/acl.py), or its anonymous mode (`occvo serve --anonymous`: a plain router, the workers
knowing a client by the zid it declares, so the guards keyed on it are advisory there). The parties: the victim is the
login `occvo serve` made for the user who started it (picked up by itself, as `occvo replay` does); an attacker comes
without credentials, with its own login (`mallory`) or with a login another user owns (`bob`), never the victim's."""

from __future__ import annotations

import atexit
import os
import shutil
import tempfile
from pathlib import Path

from occvo_services import acl, logins
from occvo_services.local import LocalService
from occvo_services.sessions import open_login

OWN, OTHER = "mallory", "bob"  # the attacker's own login, and another user's that it holds


class Deployment:
    def __init__(self, anonymous: bool):
        self.anonymous = anonymous
        self.name = "anonymous" if anonymous else "logins"
        self.folder = Path(tempfile.mkdtemp(prefix="occvo-logins-"))
        atexit.register(shutil.rmtree, self.folder, True)  # its passwords go with the run
        # the victim's clients pick up its login from here (anonymous: an empty folder, nothing to pick up)
        os.environ[logins.LOGINS_DIR_ENV] = str(self.folder)
        self.victim = None
        if anonymous:
            return
        logins.ensure(self.folder)  # the workers' logins and the user's own (the victim's)
        for login in (OWN, OTHER):
            logins.add(login, self.folder)
        self.victim = logins.default_login()

    def service(self, **kw) -> LocalService:
        """A LocalService as `occvo serve` runs it in this mode (a router config given stays: the shipped ACL).
        $OCCVO_HOSTILE_LOGS: a folder for the workers' logs (one folder a service) instead of none."""
        if os.environ.get("OCCVO_HOSTILE_LOGS") and not kw.get("log_dir"):
            kw["log_dir"] = Path(tempfile.mkdtemp(dir=os.environ["OCCVO_HOSTILE_LOGS"]))
        if self.anonymous or kw.get("router_config"):
            return LocalService(**kw)
        env = kw.pop("worker_env", None) or {}
        kw["worker_env"] = {r: {**env.get(r, {}), **acl.worker_env(r, self.folder)} for r in logins.WORKER_LOGINS}
        kw["common_args"] = [*(kw.get("common_args") or []), *acl.WORKER_ARGS]
        return LocalService(router_config=str(acl.write_router_config(self.folder)), **kw)

    def config(self, who: str) -> str | None:
        """The zenoh session config of a party: "victim", "own", "other" (None: no credentials, or anonymous)."""
        if self.anonymous or who == "none":
            return None
        login = {"victim": logins.default_login(), "own": OWN, "other": OTHER}[who]
        return str(logins.session_file(login, self.folder))

    def attacker(self, endpoint: str, who: str = "own"):
        """(session, login) of an attacker: "own" login, "other" (another user's), "none" (no credentials; the
        router refuses it in the default: NoRouterError)."""
        return open_login(endpoint, self.config(who), pick_up=False)

    def wire(self, stream: str, login: str | None) -> str:
        """A stream id as a session of `login` puts it on the wire."""
        return logins.own_stream(stream, login)

    def victim_stream(self, stream: str) -> str:
        return stream if self.anonymous else logins.own_stream(stream, self.victim)


DEPLOY: list[Deployment] = []  # the current one (hostile_clients.py sets it per pass)


def deploy() -> Deployment:
    return DEPLOY[-1]
