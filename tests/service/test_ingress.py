"""Ingress that never waits: a stream whose frames overflow its queue is answered stream_full (lossless: the client
sends the frames again, in order), and neither it nor a stream that stopped reading its poses holds up another
stream's frames."""

from __future__ import annotations

import threading
import time

import numpy as np
import zenoh
from offline import offline

from occvo_schemas import keys
from occvo_schemas.codec import encode
from occvo_services import ingress
from occvo_services.camera_frames import camera_frame_of
from occvo_services.client import OccVOClient
from occvo_services.client_sends import FULL_RETRY_S, FrameSender
from occvo_services.ingress import TurnedAway
from occvo_services.local import InProcessService
from occvo_services.sessions import open_session


def test_frames_after_one_a_full_queue_turned_away_wait_for_it_and_a_copy_of_one_in_is_not_waited_for():
    t = TurnedAway()
    for seq in range(3):
        assert t.waits("s", seq) is None
        t.entered("s", seq)
    t.turned_away("s", 3)
    assert t.waits("s", 4) == 3 and t.waits("s", 3) is None and t.waits("s", 2) is None
    t.turned_away("s", 1)  # a resend of a frame that is in: its pose comes anyway, nothing waits for it
    assert t.waits("s", 2) is None and t.waits("s", 4) == 3
    t.entered("s", 3)
    assert t.waits("s", 4) is None
    t.turned_away("s", 3)  # a late copy of 3, turned away after 3 entered: the stream does not wait for it
    assert t.waits("s", 4) is None
    t.entered("s", 4)
    t.turned_away("s", 5)
    assert t.waits("s", 0) is None and t.waits("s", 6) is None  # seq 0: a new trajectory, nothing waited for
    t.entered("s", 0)
    t.turned_away("s", 1)
    assert t.waits("s", 2) == 1 and t.waits("t", 2) is None  # one stream's wait is its own


def test_the_next_frame_still_missing_holds_the_frames_after_it_once_the_first_is_in():
    """3, 4 and 5 turned away (4 and 5 waited for 3); copies of 3 and 4 get in, 5's copy is stopped upstream (the
    inference worker's lane full) while 6 passes there: 6 waits for 5 here, it must not enter before it."""
    t = TurnedAway()
    for seq in range(3):
        t.entered("s", seq)
    for seq in (3, 4, 5):
        t.turned_away("s", seq)
    t.entered("s", 3), t.entered("s", 4)
    assert t.waits("s", 6) == 5 and t.waits("s", 5) is None
    t.entered("s", 5)
    assert t.waits("s", 6) is None


def test_a_wait_no_copy_of_its_frame_renews_ends(monkeypatch):
    """A frame turned away and never sent again (its client has its pose: a copy came after a copy of seq 0 started
    the entered frames again) holds up the stream for STALE_S at most; a copy turned away again renews the wait."""
    monkeypatch.setattr(ingress, "STALE_S", 0.2)
    t = TurnedAway()
    t.entered("s", 0)
    t.turned_away("s", 1)
    time.sleep(0.15)
    t.turned_away("s", 1)  # sent again, turned away again: still waited for
    time.sleep(0.15)
    assert t.waits("s", 2) == 1
    time.sleep(0.25)
    assert t.waits("s", 2) is None and t.waits("s", 3) is None


def test_a_copy_of_a_frame_waiting_renews_the_wait_for_the_frame_before_it(monkeypatch):
    """1 and 2 turned away, 2 waiting for 1; 1's copies are stopped upstream (a full queue there), 2's come: the
    client is sending again, so 1 is still waited for past STALE_S (else 3 would enter after a gap and 1 and 2 be
    lost); once no copy comes, the wait ends."""
    monkeypatch.setattr(ingress, "STALE_S", 0.2)
    t = TurnedAway()
    t.entered("s", 0)
    t.turned_away("s", 1), t.turned_away("s", 2)
    time.sleep(0.15)
    assert t.waits("s", 2) == 1  # a copy of 2
    t.turned_away("s", 2)
    time.sleep(0.15)
    assert t.waits("s", 3) == 1  # 0.3 s after 1 was turned away: renewed by 2's copy
    time.sleep(0.25)
    assert t.waits("s", 3) is None


def test_a_turned_away_frame_goes_again_while_the_frames_behind_it_keep_being_turned_away():
    """The retry runs from the first refusal: refusals of the frames in flight behind it, one every 0.2 s as an
    open-loop camera's would come, do not put the resend off (restarted at each, they did for as long as they came,
    and the worker gave up waiting for the frame)."""
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    with zenoh.open(config) as session:
        sent = []
        sub = session.declare_subscriber(keys.camera("s"), lambda sample: sent.append(sample.payload.to_bytes()))
        sender = FrameSender(session, "s", resend_after=60.0)
        for seq in range(3):
            sender.send(seq, f"frame {seq}".encode(), timeout=0.0)
        sender.full(1)
        end = time.monotonic() + 3 * FULL_RETRY_S
        while time.monotonic() < end and sent.count(b"frame 1") < 2:
            time.sleep(0.2)
            sender.full(2)
        sender.close()
        sub.undeclare()
    assert sent.count(b"frame 1") >= 2, sent
    assert sent.index(b"frame 1", 2) < sent.index(b"frame 2", 3)  # the turned-away frames again, in seq order
    assert sent.count(b"frame 0") == 1  # no queue turned it away: no copy of it (copies of queued frames multiplied
    # an overloaded worker's input)


def test_a_stream_overflowing_its_queue_loses_nothing_and_holds_up_no_other_stream():
    """Lossless with a queue of 2: a burst of 10 frames is partly turned away (stream_full, not an answer) and sent
    again by the client in order; every pose comes, in seq order, equal to an offline run. Beside it a stream whose
    client stopped reading its poses (its callback holds), and a stepping stream that ends complete and in order."""
    from occvo_services.commands.replay import load_scene

    burst, steady = load_scene("synthetic:6", frames=10), load_scene("synthetic:7", frames=6)
    with (
        InProcessService(queue_size=2, policy="lossless") as svc,
        OccVOClient(svc.endpoint, "burst") as b,
        OccVOClient(svc.endpoint, "steady") as s,
        OccVOClient(svc.endpoint, "stalled") as stalled,
    ):
        held = threading.Event()
        reader = open_session(svc.endpoint)  # a client that stops reading: its pose callback never returns
        sub = reader.declare_subscriber(keys.pose(stalled.stream), lambda _: held.wait(120))
        b.reset(), s.reset(), stalled.reset()
        for i in range(3):
            stalled.publish(steady[i])
        # built before: the burst goes out faster than the service answers it, however busy the host
        frames = [camera_frame_of(burst[i], b.stream, i) for i in range(10)]
        for i in range(10):
            b.publish(frames[i])  # waits by itself while turned-away frames go again
        got = [s.step(steady[i]) for i in range(6)]
        last = b.wait_pose(9, timeout=300)
        held.set()
        sub.undeclare(), reader.close()
        assert [p.seq for p in got] == list(range(6)) and not s.errors
        assert np.array_equal(np.array([p.matrix() for p in got]), offline([steady[i] for i in range(6)]).poses)
        assert last.seq == 9 and sorted(b.arrived, key=b.arrived.get) == list(range(10))  # all, in seq order
        assert np.array_equal(
            np.array([b.poses[i].matrix() for i in range(10)]), offline([burst[i] for i in range(10)]).poses
        )
        assert b.turned_away > 0 and not b.errors, b.errors  # flow control, no error
        assert (
            svc.worker("registration").stats.snapshot()[0].get("frames_refused_full", 0)
            + svc.worker("inference").stats.snapshot()[0].get("frames_refused_full", 0)
            >= 1
        )


def test_every_frame_a_full_queue_turns_away_is_told_to_its_client_whatever_its_error_budget():
    """stream_full is flow control, not an error: with a budget of one error event a client, a burst into a queue of
    1 is turned away many times, and each refusal reaches the client (a refusal it is not told of is a frame it does
    not send again, and the frames after it wait in vain); every pose comes, in order."""
    from occvo_services.commands.replay import load_scene

    burst = load_scene("synthetic:6", frames=10)
    with (
        InProcessService(queue_size=1, policy="lossless", error_events_per_s=0.01, error_burst=1) as svc,
        OccVOClient(svc.endpoint, "told") as c,
    ):
        c.reset()
        frames = [camera_frame_of(burst[i], c.stream, i) for i in range(10)]
        for f in frames:
            c.publish(f)
        assert c.wait_pose(9, timeout=300).seq == 9

        def refusals():
            return sum(w.stats.snapshot()[0].get("frames_refused_full", 0) for w in svc.workers if w.role != "map")

        deadline = time.monotonic() + 10  # the last refusals' events may be on their way
        while c.turned_away != refusals() and time.monotonic() < deadline:
            time.sleep(0.05)
        refused = refusals()
        assert refused > 1 and c.turned_away == refused, (c.turned_away, refused)
        assert sorted(c.arrived, key=c.arrived.get) == list(range(10)) and not c.errors, c.errors


def test_a_copy_of_a_frame_far_behind_the_stream_reaches_the_registration_worker(scene):
    """A full queue at registration turns frames away while the client goes on sending: a copy of a frame hundreds of
    seqs behind is still a resend of a frame the inference worker forwarded, and its pose comes back (from the stored
    trajectory here), never dropped there as out of order."""
    with InProcessService(warm_up=False) as svc, OccVOClient(svc.endpoint, "far") as c:
        c.reset()
        for _ in range(80):  # a car standing still: the same frame, 80 seqs
            c.step(scene[0])
        reg = svc.worker("registration")
        before = reg.stats.snapshot()[0].get("republished", 0)
        c.put_encoded(encode(camera_frame_of(scene[0], "far", 3)))
        deadline = time.monotonic() + 20
        while reg.stats.snapshot()[0].get("republished", 0) == before and time.monotonic() < deadline:
            time.sleep(0.05)
        assert reg.stats.snapshot()[0].get("republished", 0) == before + 1
        assert not c.errors, [(e.worker, e.code, e.message) for e in c.errors]


def test_a_stream_whose_lane_left_gives_its_place_while_its_state_is_given_back():
    """An idle stream's lane leaves before its state is given back (a snapshot of a big map takes a while): a new
    stream arriving meanwhile takes its place instead of being refused; a frame of the leaving stream keeps it."""
    from occvo_services.limits import Admission

    admission = Admission(max_streams=2, per_client=2)
    assert admission.admit("a.1", "a") is None and admission.admit("b.1", "b") is None
    assert admission.admit("c.1", "c")[0] == "stream_limit"
    admission.leaves("a.1")
    assert admission.admit("c.1", "c") is None  # over the limit by one until a.1's state is given back
    admission.release("a.1")
    assert admission.admit("d.1", "d")[0] == "stream_limit"
    admission.leaves("b.1")
    admission.stays("b.1")  # a frame came for it before it left
    assert admission.admit("d.1", "d")[0] == "stream_limit"
