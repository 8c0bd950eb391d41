"""The authenticated default of `occvo serve` and `occvo up`: the router's config written from the logins
(services/logins.py) and the access control of services/defaults/acl_router.json5 (the worker rules of
deploy/acl/router.json5, and a copy of the client rules for each client login with its prefix), and the workers run
as their logins, knowing a client by its stream ids' prefix (`client_identity: "user"`).

With a ROS 2 node (`occvo serve --ros2`, a `ros2` worker of `occvo up`), the rules of its domain's keys (rmw_zenoh's,
services/ros2/names.py): the node, as login `ros2`, subscribes its input topics and publishes its outputs; the robots'
logins (`occvo logins add NAME --ros2`) publish the inputs and subscribe the outputs; both take part in the graph
(`@ros2_lv/<domain>/**`). Every other login has no ROS 2 key. The node feeds the service as a client of its own
prefix (stream `ros2.<stream>`)."""

from __future__ import annotations

import json
from pathlib import Path

from occvo_services import defaults, logins
from occvo_services.sessions import ZENOH_CONFIG_ENV

ROUTER_FILE = "router.json5"
WORKER_ARGS = ["--client-identity", "user"]  # a client is the login whose prefix its stream ids carry
# Zenoh's messages of a topic's two sides, as the router sees them (ingress: sent by the subject; egress: delivered
# to it), on the topic's keys and its `@adv` keys (a latched topic's cache, publisher and subscriber detection)
PUBLISHER = {
    "ingress": [
        "put",
        "declare_queryable",
        "reply",
        "liveliness_token",
        "declare_liveliness_subscriber",
        "liveliness_query",
    ],
    "egress": ["declare_subscriber", "query", "liveliness_token", "reply"],  # its subscribers, history queries
}
SUBSCRIBER = {
    "ingress": ["declare_subscriber", "query", "liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
    "egress": ["put", "reply", "liveliness_token", "declare_queryable"],
}
GRAPH = {
    "ingress": ["liveliness_token", "declare_liveliness_subscriber", "liveliness_query"],
    "egress": ["liveliness_token", "reply"],
}


def ros2_nodes(up_config) -> list:
    """The settings (services/ros2/config.py) of each ROS 2 node of a deployment."""
    from occvo_services.ros2.config import Ros2NodeConfig

    return [Ros2NodeConfig.load(w.config) for w in up_config.workers if w.role == "ros2"]


def _side(rule_id: str, sides: dict, key_exprs: list[str]) -> list[dict]:
    return [
        {
            "id": f"{rule_id}_{flow}",
            "permission": "allow",
            "flows": [flow],
            "messages": messages,
            "key_exprs": key_exprs,
        }
        for flow, messages in sides.items()
    ]


def ros2_access(nodes: list, robots: list[str]) -> tuple[list, list, list]:
    """(rules, subjects, policies) of the nodes' ROS 2 domains: the node's login and the robots' on each node's
    topics and graph; none where no node runs."""
    from occvo_services.ros2.names import graph_key_expr, topic_key_exprs

    if not nodes:
        return [], [], []
    rules, node_rules, robot_rules = [], [], []
    for i, node in enumerate(nodes):
        ins = [k for t in node.inputs() for k in topic_key_exprs(node.domain_id, t)]
        outs = [k for t in node.outputs() for k in topic_key_exprs(node.domain_id, t)]
        parts = {
            "graph": (GRAPH, [graph_key_expr(node.domain_id)], True, True),
            "in_publish": (PUBLISHER, ins, False, True),  # the robot's inputs
            "in_subscribe": (SUBSCRIBER, ins, True, False),
            "out_publish": (PUBLISHER, outs, True, False),  # the node's outputs
            "out_subscribe": (SUBSCRIBER, outs, False, True),
        }
        for name, (sides, key_exprs, to_node, to_robot) in parts.items():
            made = _side(f"ros2_{i}_{name}", sides, sorted(set(key_exprs)))
            rules += made
            node_rules += [r["id"] for r in made] if to_node else []
            robot_rules += [r["id"] for r in made] if to_robot else []
    subjects = [{"id": "ros2_node", "usernames": [logins.NODE_LOGIN]}]
    policies = [{"rules": node_rules, "subjects": ["ros2_node"]}]
    if robots:
        subjects.append({"id": "ros2_robots", "usernames": list(robots)})
        policies.append({"rules": robot_rules, "subjects": ["ros2_robots"]})
    return rules, subjects, policies


def access_control(client_logins: list[str], nodes: list = (), robots: list[str] = ()) -> dict:
    """The router's access_control section: the worker rules, the client rules once for each client login, and
    with ROS 2 nodes, their domains' rules (the node's login a client of the service too)."""
    import json5

    template = json5.loads(defaults.path("acl_router.json5").read_text())
    rules, subjects, policies = list(template["rules"]), list(template["subjects"]), list(template["policies"])
    for part, made in zip((rules, subjects, policies), ros2_access(list(nodes), list(robots))):
        part += made
    for login in [*client_logins, *([logins.NODE_LOGIN] if nodes else [])]:
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


def write_router_config(folder: Path | None = None, nodes: list = ()) -> Path:
    """The router's config for this start: the built-in router's (listen endpoint, message limit) with the logins'
    dictionary and the access control of today's client logins and of the ROS 2 `nodes` (their settings). The
    workers' logins are created if missing and, on a first start, the client login of the user running this."""
    import json5

    folder = folder or logins.logins_dir()
    logins.ensure(folder, node=bool(nodes))
    config = json5.loads(defaults.path("router.json5").read_text())
    auth = config.setdefault("transport", {}).setdefault("auth", {})
    auth["usrpwd"] = {"dictionary_file": str((folder / logins.USERS_FILE).resolve())}
    config["access_control"] = access_control(logins.client_logins(folder), nodes, logins.ros2_logins(folder))
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
    nodes = ros2_nodes(up_config)
    logins.ensure(folder, node=bool(nodes))
    probe = probe_config(folder)  # before the router's config: it may add a login
    up_config.router.config = str(write_router_config(folder, nodes))
    for w in up_config.workers:
        w.env = {**w.env, **worker_env(w.role, folder)}
        w.args = [*w.args, *WORKER_ARGS] if w.role != "ros2" else w.args  # the node is a client, its own prefix
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

    def __init__(self, folder: Path | None = None, every_s: float = 1.0, nodes: list = ()):
        self.folder = folder or logins.logins_dir()
        self.every_s, self._next, self.nodes = every_s, 0.0, list(nodes)
        self._stamp = self._look()

    def _look(self):
        stamps = []
        for name in (logins.USERS_FILE, logins.ROS2_FILE):
            try:
                st = (self.folder / name).stat()
            except OSError:
                stamps.append(None)
                continue
            stamps.append((st.st_mtime_ns, st.st_size, st.st_ino))
        return stamps

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
        write_router_config(self.folder, self.nodes)
        return True
