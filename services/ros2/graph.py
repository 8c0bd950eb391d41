"""A ROS 2 node on a Zenoh session, as rmw_zenoh makes one: a liveliness token for the node and for each publisher
and subscription (so `ros2 node list` / `ros2 topic list` see them), samples on the topics' keys with CDR payloads
and rmw_zenoh's attachment; a transient-local publisher keeps its last messages for late subscribers."""

from __future__ import annotations

import itertools
import logging
import threading
import time
from collections.abc import Callable

import zenoh
import zenoh.ext

from occvo_core.viz.ros_messages import STORE
from occvo_services.ros2.attachment import Attachment
from occvo_services.ros2.names import RELIABLE, TRANSIENT_LOCAL, NodeName, QoS, gid, resolve, topic_key
from occvo_services.ros2.type_hash import rihs01
from occvo_services.telemetry import log_event


class Publisher:
    def __init__(self, pub, ros_type: str, gid_: bytes):
        self._pub, self.ros_type, self.gid = pub, ros_type, gid_
        self._seq = itertools.count(1)  # rmw_zenoh numbers a publisher's samples from 1
        self._lock = threading.Lock()

    def publish(self, msg) -> None:
        payload = bytes(STORE.serialize_cdr(msg, self.ros_type))  # little-endian CDR after its 4-byte header
        with self._lock:
            att = Attachment(next(self._seq), time.time_ns(), self.gid).encode()
            self._pub.put(payload, attachment=att)


class Ros2Graph:
    """One node of a ROS 2 domain on `session`; close() takes it and its topics out of the graph."""

    def __init__(self, session: zenoh.Session, domain_id: int, name: str, namespace: str, log: logging.Logger):
        self.session, self.domain_id, self.namespace, self.log = session, domain_id, namespace, log
        self._ids = itertools.count(1)  # rmw_zenoh counts a context's entities, the node first
        self.node = NodeName(domain_id, str(session.info.zid()), 0, name, namespace)
        self._decls: list = [session.liveliness().declare_token(self.node.node_token())]
        self.bad_messages = 0
        self.lost_messages = 0  # messages a publisher numbered that never came (rmw_zenoh's attachment)
        self._count = threading.Lock()  # lost_messages and each subscription's last sequence numbers

    def _endpoint(self, kind: str, topic: str, ros_type: str, qos: QoS) -> tuple[str, str, bytes]:
        topic = resolve(topic, self.namespace)
        type_hash = rihs01(STORE, ros_type)
        token = self.node.endpoint_token(next(self._ids), kind, topic, ros_type, type_hash, qos)
        self._decls.append(self.session.liveliness().declare_token(token))
        return topic, topic_key(self.domain_id, topic, ros_type, type_hash), gid(token)

    def publisher(self, topic: str, ros_type: str, qos: QoS) -> Publisher:
        _, key, g = self._endpoint("MP", topic, ros_type, qos)
        reliability = zenoh.Reliability.RELIABLE if qos.reliability == RELIABLE else zenoh.Reliability.BEST_EFFORT
        if qos.durability == TRANSIENT_LOCAL:  # as rmw_zenoh: a cache of `depth` samples, found by late subscribers
            pub = zenoh.ext.declare_advanced_publisher(
                self.session,
                key,
                reliability=reliability,
                cache=zenoh.ext.CacheConfig(max_samples=qos.depth),
                publisher_detection=True,
            )
        else:
            pub = self.session.declare_publisher(key, reliability=reliability)
        self._decls.append(pub)
        return Publisher(pub, ros_type, g)

    def subscribe(self, topic: str, ros_type: str, handler: Callable, qos: QoS) -> None:
        """handler(msg) for each message; a message that is not CDR of ros_type is logged in one line and dropped."""
        topic, key, _ = self._endpoint("MS", topic, ros_type, qos)
        # publisher gid -> its last sequence number; a latched topic's history comes beside its live samples, in no
        # order with them: no gaps counted there
        last_seen: dict[bytes, int] | None = None if qos.durability == TRANSIENT_LOCAL else {}

        def on_sample(sample: zenoh.Sample) -> None:
            lost = self._count_lost(last_seen, sample.attachment) if last_seen is not None else 0
            if lost:
                log_event(self.log, "ros messages lost", logging.WARNING, topic=topic, lost=lost)
            try:
                msg = STORE.deserialize_cdr(sample.payload.to_bytes(), ros_type)
            except Exception as exc:  # noqa: BLE001 - any decoder failure is the sender's bad message
                self.bad_messages += 1
                log_event(
                    self.log, "bad ros message", logging.WARNING, topic=topic, type=ros_type, error=str(exc)[:200]
                )
                return
            try:
                handler(msg)
            except Exception as exc:  # noqa: BLE001 - one bad message never takes the node down
                self.bad_messages += 1
                log_event(self.log, "ros message refused", logging.WARNING, topic=topic, error=str(exc)[:300])

        if qos.durability == TRANSIENT_LOCAL:  # a latched topic: what its publishers kept, then what comes
            history = zenoh.ext.HistoryConfig(detect_late_publishers=True, max_samples=qos.depth)
            sub = zenoh.ext.declare_advanced_subscriber(self.session, key, on_sample, history=history)
        else:
            sub = self.session.declare_subscriber(key, on_sample)
        self._decls.append(sub)

    def _count_lost(self, last_seen: dict[bytes, int], attachment) -> int:
        """Messages lost before this sample, from the sequence numbers rmw_zenoh's publishers put on each one (a
        keep-last publisher drops samples under congestion): a number that skips ahead counts the ones between; one
        that goes back is a publisher that started again; a sample without rmw_zenoh's attachment counts nothing."""
        if attachment is None:
            return 0
        try:
            a = Attachment.decode(attachment.to_bytes())
        except ValueError:
            return 0  # not rmw_zenoh's
        with self._count:
            last = last_seen.get(a.source_gid)
            last_seen[a.source_gid] = a.sequence_number
            lost = a.sequence_number - last - 1 if last is not None and a.sequence_number > last + 1 else 0
            self.lost_messages += lost
        return lost

    def close(self) -> None:
        for d in reversed(self._decls):
            d.undeclare()
        self._decls.clear()
