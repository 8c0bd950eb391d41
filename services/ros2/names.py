"""rmw_zenoh's names on Zenoh (Jazzy, Kilted): the data key of a topic, the liveliness tokens of a node and of its
publishers and subscriptions (the ROS 2 graph), the QoS text in a token, and an entity's gid."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

ADMIN_SPACE = "@ros2_lv"
# rmw's enum values; rmw_zenoh leaves a field empty where it equals its default (reliable, volatile, keep last 42,
# infinite deadline, lifespan and lease, automatic liveliness)
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
_DEFAULT = {"reliability": RELIABLE, "durability": VOLATILE, "history": KEEP_LAST, "depth": 42}


@dataclass(frozen=True)
class QoS:
    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = 10

    def token(self) -> str:
        """`<reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:<liveliness>,<s>,<ns>`,
        each field empty at rmw_zenoh's default."""

        def f(name: str) -> str:
            v = getattr(self, name)
            return "" if v == _DEFAULT[name] else str(v)

        return f"{f('reliability')}:{f('durability')}:{f('history')},{f('depth')}:,:,:,,"


SENSOR_QOS = QoS()  # reliable, volatile, keep last 10: rclcpp's default profile
LATCHED_QOS = QoS(durability=TRANSIENT_LOCAL, depth=1)  # a late subscriber gets the last message (/occvo/map)


def mangle(name: str) -> str:
    """A ROS name inside one key chunk: '/' becomes '%' (the empty namespace '/' is '%')."""
    return name.replace("/", "%")


def dds_type_name(ros_type: str) -> str:
    """`nav_msgs/msg/Odometry` -> `nav_msgs::msg::dds_::Odometry_`, the type name rmw_zenoh's type support gives."""
    pkg, kind, name = ros_type.split("/")
    return f"{pkg}::{kind}::dds_::{name}_"


def resolve(topic: str, namespace: str) -> str:
    """A relative topic name under the node's namespace; an absolute one as it is."""
    if topic.startswith("/"):
        return topic
    return namespace.rstrip("/") + "/" + topic


def topic_key(domain_id: int, topic: str, ros_type: str, type_hash: str) -> str:
    """`<domain>/<topic without its leading and trailing '/'>/<dds type name>/<RIHS01 hash>`: the samples' key."""
    return f"{domain_id}/{topic.strip('/')}/{dds_type_name(ros_type)}/{type_hash}"


def topic_key_exprs(domain_id: int, topic: str) -> list[str]:
    """What a topic takes on Zenoh, for access control: its samples' keys (any type, any hash) and zenoh-ext's keys
    of its advanced publishers and subscribers (`@adv`: the latched cache, publisher and subscriber detection)."""
    key = f"{domain_id}/{topic.strip('/')}/*/*"
    return [key, f"{key}/@adv/**"]


def graph_key_expr(domain_id: int) -> str:
    """Every liveliness token of a domain's graph: its nodes, publishers and subscriptions."""
    return f"{ADMIN_SPACE}/{domain_id}/**"


@dataclass(frozen=True)
class NodeName:
    domain_id: int
    zid: str  # the Zenoh session's id as zenoh prints it
    node_id: int
    name: str
    namespace: str = "/"
    enclave: str = "/"

    def _prefix(self, entity_id: int, kind: str) -> str:
        return (
            f"{ADMIN_SPACE}/{self.domain_id}/{self.zid}/{self.node_id}/{entity_id}/{kind}/"
            f"{mangle(self.enclave)}/{mangle(self.namespace)}/{mangle(self.name)}"
        )

    def node_token(self) -> str:
        return self._prefix(self.node_id, "NN")

    def endpoint_token(self, entity_id: int, kind: str, topic: str, ros_type: str, type_hash: str, qos: QoS) -> str:
        """kind: MP (publisher) or MS (subscription)."""
        return (
            f"{self._prefix(entity_id, kind)}/{mangle(topic)}/{mangle(dds_type_name(ros_type))}/{type_hash}/"
            f"{qos.token()}"
        )


def gid(token: str) -> bytes:
    """An entity's 16-byte gid, from its liveliness token as rmw_zenoh derives it; rmw_zenoh takes XXH3-128 of the
    token, here BLAKE2b-128: receivers only compare gids, so any 16 bytes unique to the entity serve."""
    return hashlib.blake2b(token.encode(), digest_size=16).digest()
