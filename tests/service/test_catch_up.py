"""A session reopened from the store registers before the other lanes' next frames (scheduling.CatchUp)."""

import threading

from occvo_services.registration.scheduling import CatchUp


def _lane(gate: CatchUp, stream: str, passed: list) -> threading.Thread:
    t = threading.Thread(target=lambda: (gate.wait_turn(stream), passed.append(stream)))
    t.start()
    return t


def test_other_lanes_wait_until_every_catching_up_session_is_through():
    gate, passed = CatchUp(max_wait_s=600.0), []
    gate.begin("moved-a")
    gate.begin("moved-b")
    gate.wait_turn("moved-a")  # a catching-up session never waits for itself or the others catching up
    other = _lane(gate, "steady", passed)
    gate.end("moved-a")
    other.join(0.2)
    assert passed == [] and other.is_alive()  # one session still catches up: the lane still waits
    gate.end("moved-b")
    other.join(600.0)
    assert passed == ["steady"]


def test_a_lane_waits_at_most_max_wait_s_and_not_at_all_when_no_one_catches_up():
    gate, passed = CatchUp(max_wait_s=0.05), []
    _lane(gate, "steady", passed).join(600.0)
    gate.begin("moved")
    _lane(gate, "steady", passed).join(600.0)  # a long replay holds the others up to max_wait_s, no longer
    gate.end("moved")
    gate.end("never-began")  # ending a session that did not catch up is nothing
    assert passed == ["steady", "steady"]
