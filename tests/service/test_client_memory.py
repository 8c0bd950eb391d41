"""A client that runs for hours (the ROS 2 node's) keeps a bounded record: forget() drops the poses it has used, and
the error events it keeps are the latest MAX_ERRORS. Real Zenoh sessions on loopback, the workers as threads."""

from __future__ import annotations

import time

import pytest
import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_schemas.models import ErrorEvent
from occvo_services.client import MAX_ERRORS, OccVOClient
from occvo_services.local import InProcessService
from occvo_services.sessions import open_session


@pytest.fixture(scope="module")
def service():
    with InProcessService() as svc:
        yield svc


def test_forget_drops_the_poses_up_to_a_seq_and_keeps_the_rest(service, scene):
    with OccVOClient(service.endpoint, stream="hours") as env:
        env.reset()
        for f in scene[:3]:
            env.step(f)
        assert sorted(env.poses) == sorted(env.arrived) == [0, 1, 2]
        env.forget(1)
        assert sorted(env.poses) == sorted(env.arrived) == [2]
        assert env.wait_pose(2).seq == 2  # what was not forgotten is still there


def test_the_client_keeps_the_latest_error_events_only(service):
    extra = 50
    with OccVOClient(service.endpoint, stream="noisy") as env:
        other = open_session(service.endpoint)  # the events as a worker would publish them
        try:
            key = keys.errors(env.stream)
            for seq in range(MAX_ERRORS + extra):
                event = ErrorEvent(stream=env.stream, worker="test", code="invalid_frame", message="bad", seq=seq)
                other.put(key, encode(event), congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline and not (env.errors and env.errors[-1].seq == MAX_ERRORS + extra - 1):
                time.sleep(0.05)
        finally:
            other.close()
        assert [e.seq for e in env.errors] == list(range(extra, MAX_ERRORS + extra))
