"""A stream beside noisy neighbours on the same workers: one whose frames hold ten times the voxels (its
registration several times a normal frame's) and one whose client stopped reading its poses. The steady stream's
poses all come, in order, equal to an offline run, and so do the heavy stream's; no frame of one stream waits in the
kernel team's queue behind another stream's."""

from __future__ import annotations

import logging
import threading

import numpy as np
from offline import offline

from occvo_core import OccVO
from occvo_core.sim.heavy import HeavyScene, thicken
from occvo_schemas import keys
from occvo_services.client import OccVOClient
from occvo_services.commands.replay import load_scene
from occvo_services.local import InProcessService
from occvo_services.registration.scheduling import Scheduler
from occvo_services.sessions import open_session
from occvo_services.telemetry import Stats


def test_a_heavy_frame_holds_ten_times_the_voxels_each_once_with_the_frames_own_among_them():
    frame = load_scene("synthetic:3", frames=1)[0]
    heavy = thicken(frame)
    assert len(heavy.points) == 10 * len(frame.points)
    assert len(np.unique(heavy.points, axis=0)) == len(heavy.points)  # a set of voxels: none twice
    own = {tuple(p) for p in frame.points}
    assert own <= {tuple(p) for p in heavy.points}


def test_a_call_for_the_kernel_team_while_another_holds_it_runs_at_once_in_its_own_thread():
    stats = Stats()
    scheduler = Scheduler(0, stats, logging.getLogger("test"))
    vo = OccVO()
    vo.threads = 2  # would go to the team
    release = threading.Event()
    holder = threading.Thread(target=scheduler.kernels, args=(vo, release.wait, 30))
    holder.start()
    try:
        while not scheduler._team_busy:  # the holder's call is in the team
            release.wait(0.01)
        ran_in = []  # the thread the call ran in: its caller's, while the team is held (not queued behind it)
        beside = threading.Thread(target=lambda: ran_in.append(scheduler.kernels(vo, threading.get_ident)[0]))
        beside.start()
        beside.join(20)
        assert ran_in == [beside.ident] and stats.counters["kernels_beside_team"] == 1
        scheduler.kernels_done(2)  # a frame done in its lane: the busy team's OpenMP threads are left alone
        assert scheduler._idle_team.nice is None
        me = threading.get_ident()
        release.set()
        holder.join()
        result, _ = scheduler.kernels(vo, threading.get_ident)  # the team free again: the call goes to it
        assert result != me
    finally:
        release.set()
        holder.join()
        scheduler.shutdown(), scheduler.close_pools()


def test_a_stream_beside_a_heavy_stream_and_one_that_stopped_reading_gets_every_pose_in_order():
    """The heavy stream sends its frames at once (lossless: its full queue turns some away, sent again in order),
    the stalled stream's pose callback never returns; the steady stream steps its frames meanwhile."""
    heavy, steady = HeavyScene(load_scene("synthetic:8", frames=6)), load_scene("synthetic:9", frames=8)
    with (
        InProcessService(queue_size=2, policy="lossless") as svc,
        OccVOClient(svc.endpoint, "heavy") as h,
        OccVOClient(svc.endpoint, "steady") as s,
        OccVOClient(svc.endpoint, "stalled") as stalled,
    ):
        held = threading.Event()
        reader = open_session(svc.endpoint)  # a client that stops reading: its pose callback never returns
        sub = reader.declare_subscriber(keys.pose(stalled.stream), lambda _: held.wait(600))
        try:
            h.reset(), s.reset(), stalled.reset()
            for i in range(4):
                stalled.publish(steady[i])
            sender = threading.Thread(target=lambda: [h.publish(heavy[i]) for i in range(6)])
            sender.start()
            # a pose held up until the stalled client's callback returned would be a TimeoutError here
            got = [s.wait_pose(s.publish(steady[i]), timeout=120) for i in range(8)]
            sender.join()
            last = h.wait_pose(5, timeout=300)
        finally:
            held.set()
            sub.undeclare(), reader.close()
        assert [p.seq for p in got] == list(range(8)) and sorted(s.arrived, key=s.arrived.get) == list(range(8))
        assert not s.errors and not h.errors, (s.errors, h.errors)
        assert np.array_equal(np.array([p.matrix() for p in got]), offline([steady[i] for i in range(8)]).poses)
        assert last.seq == 5 and sorted(h.arrived, key=h.arrived.get) == list(range(6))
        assert np.array_equal(
            np.array([h.poses[i].matrix() for i in range(6)]), offline([heavy[i] for i in range(6)]).poses
        )
