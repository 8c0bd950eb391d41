"""The logins of the router that `occvo serve` and `occvo up` run: one for each worker role and one for each client
(a user, a host, a robot), with random passwords, in files readable by their owner only, in one folder
($OCCVO_LOGINS_DIR, else $XDG_CONFIG_HOME/occvo/logins, else ~/.config/occvo/logins), as Jupyter keeps its token:

    users.txt                 the router's user:password dictionary (zenoh usrpwd)
    session-<login>.json5     the zenoh client config of each login (OCCVO_ZENOH_CONFIG, or picked up by itself)
    router.json5              the router's config, written from the logins at each start (services/acl.py)
    ros2.txt                  the client logins also allowed onto the ROS 2 graph of `occvo serve --ros2` (robots)

A client login publishes and follows only the streams whose id starts with `<login>.` (the access control), so the
workers know a client by that prefix (`client_identity: "user"`), not by anything the client says about itself."""

from __future__ import annotations

import getpass
import json
import os
import re
import secrets
from pathlib import Path

from occvo_core.errors import ConfigError

LOGINS_DIR_ENV = "OCCVO_LOGINS_DIR"
WORKER_LOGINS = ("inference", "registration", "map")
NODE_LOGIN = "ros2"  # occvo's ROS 2 node (`occvo serve --ros2`): a worker's login, made where a node runs
RESERVED = (*WORKER_LOGINS, NODE_LOGIN)
USERS_FILE = "users.txt"
ROS2_FILE = "ros2.txt"
LOGIN_RE = re.compile(r"^[A-Za-z0-9_-]{1,32}$")  # a stream id's prefix: no '.', no key expression characters


def logins_dir() -> Path:
    if os.environ.get(LOGINS_DIR_ENV):
        return Path(os.environ[LOGINS_DIR_ENV]).expanduser()
    base = os.environ.get("XDG_CONFIG_HOME") or Path.home() / ".config"
    return Path(base) / "occvo" / "logins"


def check_login(name: str) -> str:
    if not LOGIN_RE.match(name or ""):
        raise ConfigError(f"login {name!r}: 1 to 32 letters, digits, '_' or '-' (it is the prefix of its stream ids)")
    return name


def default_login() -> str:
    """The client login of the user running this: their user name, made a valid prefix (a worker's name is taken)."""
    name = re.sub(r"[^A-Za-z0-9_-]", "-", getpass.getuser())[:32] or "user"
    return f"{name}-client"[:32] if name in RESERVED else name


def session_file(login: str, folder: Path | None = None) -> Path:
    return (folder or logins_dir()) / f"session-{login}.json5"


def write_private(path: Path, text: str) -> None:
    """Write `text` to a file only its owner may read, replacing it whole (never a half-written password file)."""
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def read_users(folder: Path | None = None) -> dict[str, str]:
    """login -> password, from the router's dictionary (empty when there is none yet)."""
    path = (folder or logins_dir()) / USERS_FILE
    if not path.is_file():
        return {}
    users = {}
    for line in path.read_text().splitlines():
        name, sep, password = line.partition(":")
        if sep and name:
            users[name] = password
    return users


def _write_users(users: dict[str, str], folder: Path) -> None:
    write_private(folder / USERS_FILE, "".join(f"{u}:{p}\n" for u, p in users.items()))


def session_text(login: str, password: str) -> str:
    """A zenoh client config logging in as `login` (the router's endpoint comes from --connect or the code)."""
    auth = json.dumps({"user": login, "password": password})
    return (
        f"// The zenoh client config of occvo login {login} (OCCVO_ZENOH_CONFIG=<this file>): it holds the "
        "password, keep it to its owner.\n"
        f'{{\n  mode: "client",\n  scouting: {{ multicast: {{ enabled: false }} }},\n'
        f"  metadata: {{ occvo_login: {json.dumps(login)} }},  // its clients prefix their stream ids with it\n"
        f"  transport: {{ auth: {{ usrpwd: {auth} }} }},\n}}\n"
    )


def add(name: str, folder: Path | None = None, write: bool = True, ros2: bool = False) -> str:
    """A new client login with a random password; returns its session config (written next to the others when
    `write`, else only returned, e.g. to be printed for another host). `ros2`: a robot's, also allowed onto the ROS 2
    graph of `occvo serve --ros2` (services/acl.py)."""
    folder = folder or logins_dir()
    check_login(name)
    if name in RESERVED:
        raise ConfigError(f"login {name!r} is a worker's: choose another name")
    users = read_users(folder)
    if name in users:
        raise ConfigError(f"login {name!r} exists already (occvo logins remove {name} first)")
    _write_ros2(name, ros2, folder)  # before the dictionary, which a running serve watches: it reads both then
    users[name] = secrets.token_urlsafe(24)
    _write_users(users, folder)
    text = session_text(name, users[name])
    if write:
        write_private(session_file(name, folder), text)
    return text


def remove(name: str, folder: Path | None = None) -> None:
    folder = folder or logins_dir()
    if name in RESERVED:
        raise ConfigError(f"login {name!r} is a worker's and cannot be removed")
    users = read_users(folder)
    if name not in users:
        raise ConfigError(f"no login {name!r} in {folder / USERS_FILE}")
    del users[name]
    _write_users(users, folder)
    _write_ros2(name, False, folder)
    session_file(name, folder).unlink(missing_ok=True)


def client_logins(folder: Path | None = None) -> list[str]:
    return sorted(u for u in read_users(folder) if u not in RESERVED)


def ros2_logins(folder: Path | None = None) -> list[str]:
    """The client logins a robot's ROS 2 processes log in with (`occvo logins add NAME --ros2`)."""
    path = (folder or logins_dir()) / ROS2_FILE
    named = set(path.read_text().split()) if path.is_file() else set()
    return [u for u in client_logins(folder) if u in named]


def _write_ros2(name: str, ros2: bool, folder: Path) -> None:
    path = folder / ROS2_FILE
    named = set(path.read_text().split()) if path.is_file() else set()
    if (name in named) != ros2:
        write_private(path, "".join(f"{u}\n" for u in sorted(named ^ {name})))


def ensure(folder: Path | None = None, node: bool = False) -> dict[str, str]:
    """The workers' logins (`node`: the ROS 2 node's too) and, on a first start, one client login for the user
    running this: created where missing, with their session configs. Returns every login and its password."""
    folder = folder or logins_dir()
    users = read_users(folder)
    first = not users
    for login in (*WORKER_LOGINS, NODE_LOGIN) if node else WORKER_LOGINS:
        if login not in users or not session_file(login, folder).is_file():
            # a worker running with its file's password keeps it (users.txt edited by hand): never a new one then
            users[login] = users.get(login) or _password_of(session_file(login, folder)) or secrets.token_urlsafe(24)
            _write_users(users, folder)
            write_private(session_file(login, folder), session_text(login, users[login]))
    if first:
        add(default_login(), folder)
        users = read_users(folder)
    return users


def _password_of(path: Path) -> str | None:
    import json5

    try:
        return json5.loads(path.read_text())["transport"]["auth"]["usrpwd"]["password"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def own_client_config() -> Path | None:
    """The session config of this user's client login, when `occvo serve` made one here (None otherwise)."""
    path = session_file(default_login())
    return path if path.is_file() else None


def login_of(config_path: str | Path | None) -> str | None:
    """The occvo login a zenoh session config logs in as: its `metadata.occvo_login`, which the files written here
    carry (None: none, or not readable). A hand-written config (deploy/acl/: a viewer reads every stream) has none,
    and its clients' stream ids are taken as given."""
    if not config_path:
        return None
    import json5

    try:
        user = json5.loads(Path(config_path).read_text())["metadata"]["occvo_login"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return user if isinstance(user, str) and LOGIN_RE.match(user) else None


def own_stream(stream: str, login: str | None) -> str:
    """The stream id on the wire: `stream` under the login's prefix (kept when it has it already)."""
    if not login or stream.startswith(f"{login}."):
        return stream
    return f"{login}.{stream}"
