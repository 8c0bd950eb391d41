"""The ROS 2 node's graph counts and logs the input messages lost on the way (a keep-last rmw_zenoh publisher drops
samples under congestion: a cloud that never came is a pose that never comes), from the sequence numbers on each
sample's rmw_zenoh attachment. A real router and sessions on loopback."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest

pytest.importorskip("rosbags", reason="rosbags (the ros extra) holds the ROS message types")

from occvo_core.viz import ros_messages as rm  # noqa: E402
from occvo_services.ros2.attachment import Attachment  # noqa: E402
from occvo_services.ros2.graph import Ros2Graph  # noqa: E402
from occvo_services.ros2.names import LATCHED_QOS, SENSOR_QOS, topic_key  # noqa: E402
from occvo_services.ros2.type_hash import rihs01  # noqa: E402
from occvo_services.sessions import free_port, open_router, open_session  # noqa: E402

TF = "tf2_msgs/msg/TFMessage"


class Lines(logging.Handler):
    def __init__(self):
        super().__init__()
        self.lines: list[tuple[str, dict]] = []

    def emit(self, record):
        self.lines.append((record.getMessage(), getattr(record, "fields", {})))


def test_a_publishers_skipped_sequence_numbers_are_counted_and_logged_once_a_gap():
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    node_session, robot = open_session(endpoint, pick_up=False), open_session(endpoint, pick_up=False)
    log = logging.getLogger("occvo.test-ros2-input-loss")
    lines = Lines()
    log.addHandler(lines)
    try:
        graph = Ros2Graph(node_session, 7, "occvo", "/robot1", log)
        got = []
        latched = []
        graph.subscribe("/tf", TF, got.append, SENSOR_QOS)
        graph.subscribe("/tf_static", TF, latched.append, LATCHED_QOS)
        payload = bytes(rm.STORE.serialize_cdr(rm.transform(1, np.eye(4), "odom", "base_link"), TF))
        pub = robot.declare_publisher(topic_key(7, "/tf", TF, rihs01(rm.STORE, TF)))
        static = robot.declare_publisher(topic_key(7, "/tf_static", TF, rihs01(rm.STORE, TF)))
        time.sleep(1.0)  # the subscriptions' routes
        for seq in (1, 5):  # a latched topic: its history comes beside live samples, in no order; not counted
            static.put(payload, attachment=Attachment(seq, time.time_ns(), b"S" * 16).encode())
        # publisher A: 1, 2, then 5 (3 and 4 lost); publisher B: 1, 2; A again from 1 (it started again); no attachment
        for gid, seq in [(b"A" * 16, 1), (b"A" * 16, 2), (b"B" * 16, 1), (b"A" * 16, 5), (b"B" * 16, 2)]:
            pub.put(payload, attachment=Attachment(seq, time.time_ns(), gid).encode())
        pub.put(payload, attachment=Attachment(1, time.time_ns(), b"A" * 16).encode())
        pub.put(payload)
        deadline = time.monotonic() + 10
        while (len(got) < 7 or len(latched) < 2) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert len(got) == 7 and len(latched) == 2 and graph.bad_messages == 0
        assert graph.lost_messages == 2
        assert [f for event, f in lines.lines if event == "ros messages lost"] == [{"topic": "/tf", "lost": 2}]
        graph.close()
    finally:
        log.removeHandler(lines)
        robot.close()
        node_session.close()
        router.close()
