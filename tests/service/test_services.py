"""Services on real Zenoh sessions (router + three workers as threads of the test process, random loopback port):
bad input of every kind is reported and survived, good frames give the offline poses, flow policies, several streams."""

from __future__ import annotations

import contextlib
import os
import resource
import threading
import time
import warnings
from pathlib import Path

import msgpack
import numpy as np
import pytest
import zenoh
from offline import offline

from occvo_core.map_tiles import changed_tiles, tiles_from_map
from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import Array, ErrorEvent, OccupancyFrameMsg, SparseOccupancy
from occvo_services.client import OccVOClient, ServiceError, camera_frame_of
from occvo_services.local import InProcessService
from occvo_services.runtime import SeqTracker, StageQueue
from occvo_services.sessions import open_session

DATA = Path(__file__).resolve().parents[3] / "shared/data/occvo-sample"
SCENE = DATA / "occupancy/scene-0101"
needs_data = pytest.mark.skipif(not SCENE.is_dir(), reason=f"sample data not found at {SCENE}")
warnings.filterwarnings("ignore", category=RuntimeWarning)


def scene(name="scene-0101"):
    from occvo_core.datasets.occvo_release import OccVOReleaseScene

    return OccVOReleaseScene(DATA / "occupancy" / name)


# ------------------------------------------------------------------ pure parts


def test_stage_queue_latest_drops_oldest_and_counts():
    dropped = []
    q = StageQueue(2, "latest", dropped.append, threading.Event())
    for i in range(5):
        assert q.put(i)
    assert dropped == [0, 1, 2] and [q.get(0.1), q.get(0.1)] == [3, 4]


def test_stage_queue_lossless_never_drops_refuses_when_full_and_gives_up_on_stop():
    """Lossless keeps every queued item in order; a full queue refuses the new one at once (its sender is answered
    stream_full and sends it again: services/ingress.py), never waits in the caller's thread."""
    stop = threading.Event()
    q = StageQueue(1, "lossless", lambda _: pytest.fail("lossless never drops"), stop)
    assert q.put("a")
    t0 = time.monotonic()
    assert q.put("b") is False and time.monotonic() - t0 < 0.05  # refused, not waited for
    assert q.get(0.1) == "a"
    assert q.put("b") and q.get(0.1) == "b"
    q.put("c")
    stop.set()
    assert q.put("d") is False


def test_seq_tracker():
    t = SeqTracker()
    assert t.check(0) == (True, None, None)
    assert t.check(1)[0]
    ok, code, msg = t.check(4)
    assert ok and code == "missing_seq" and "2..3" in msg
    assert t.check(2) == (True, None, None)  # the jump to 4 not adopted: the real next frame goes on
    assert t.check(9)[1] == "missing_seq" and t.check(10) == (True, None, None)  # a jump confirmed by its next seq
    ok, code, _ = t.check(3)
    assert not ok and code == "out_of_order"
    assert t.check(0) == (True, None, None)  # a new trajectory
    assert t.check(1)[0]


def test_tiles_partition_the_map_and_diff():
    rng = np.random.default_rng(1)
    pts = rng.uniform(-70, 70, (5000, 3))
    labels = rng.integers(0, 17, 5000).astype(np.uint8)
    tiles = tiles_from_map(pts, labels, 20.0)
    assert sum(len(p) for p, _ in tiles.values()) == len(pts)
    for (ix, iy), (p, _labels) in tiles.items():
        assert np.all(np.floor(p[:, :2] / 20.0) == [ix, iy])
    back = np.concatenate([p for p, _ in tiles.values()])
    assert np.array_equal(np.unique(back, axis=0), np.unique(pts, axis=0))
    assert changed_tiles(tiles, tiles) == {}
    moved = pts.copy()
    moved[0] = [1.0, 1.0, 0.0]  # into tile (0, 0)
    diff = changed_tiles(tiles, tiles_from_map(moved, labels, 20.0))
    old_key = tuple(np.floor(pts[0, :2] / 20).astype(int))
    assert (0, 0) in diff and old_key in diff and len(diff) <= 2
    gone = changed_tiles(tiles, {})
    assert set(gone) == set(tiles) and all(len(p) == 0 for p, _ in gone.values())
    with pytest.raises(ValueError):
        tiles_from_map(pts, labels, 0.0)


# ------------------------------------------------------------------ service


class ErrorLog:
    def __init__(self, session, stream="*"):
        self.events: list[ErrorEvent] = []
        self.sub = session.declare_subscriber(
            keys.errors(stream), lambda s: self.events.append(decode(s.payload.to_bytes(), ErrorEvent))
        )

    def make_live(self, session, key, timeout=20.0):
        """Send garbage to `key` until its error event comes back (this subscriber has reached the router), then
        forget those events: without it, the first events of a test can be published before anyone listens."""
        deadline = time.monotonic() + timeout
        while not self.events and time.monotonic() < deadline:
            session.put(key, b"\xc1")
            time.sleep(0.2)
        time.sleep(0.5)
        self.events.clear()

    def wait(self, n, timeout=10.0):
        return self.wait_until(lambda events: len(events) >= n, timeout)

    def wait_until(self, done, timeout=10.0):
        """Events so far, once done(events) holds or the timeout passes (two workers report in either order)."""
        deadline = time.monotonic() + timeout
        while not done(list(self.events)) and time.monotonic() < deadline:
            time.sleep(0.02)
        return list(self.events)


@pytest.fixture(scope="module")
def service():
    with InProcessService(max_message_bytes=2_000_000) as svc:
        yield svc


@needs_data
def test_bad_input_is_reported_and_good_poses_still_come(service):
    s, n = scene(), 4
    frames = [s[i] for i in range(n)]
    session = open_session(service.endpoint)
    errors = ErrorLog(session, "bad")
    errors.make_live(session, keys.camera("bad"))
    good = camera_frame_of(frames[0], "bad", 0)
    as_points = SparseOccupancy(points=Array.from_numpy(frames[0].points), labels=good.gt_occupancy.labels)
    good = good.model_copy(update={"gt_occupancy": as_points})  # float64 coordinates: the bytes bent below
    raw = msgpack.unpackb(encode(good), raw=False)

    def variant(mutate):
        d = msgpack.unpackb(encode(good), raw=False)
        mutate(d)
        return msgpack.packb(d, use_bin_type=True)

    pts = frames[0].points.copy()
    pts[5, 2] = np.nan
    labels = frames[0].labels.copy()
    labels[9] = 77

    def set_(path, value):
        def f(d):
            for p in path[:-1]:
                d = d[p]
            d[path[-1]] = value

        return f

    bad_inputs = {
        "malformed": b"\x92\xc1\xff not msgpack",
        "unknown_kind": msgpack.packb({**raw, "kind": "telepathy"}),
        "unsupported_version": variant(set_(["schema_version"], 99)),
        "wrong_array_size": variant(set_(["gt_occupancy", "points", "data"], pts.tobytes()[:-24])),
        "nan": variant(set_(["gt_occupancy", "points", "data"], pts.tobytes())),
        "labels_out_of_range": variant(set_(["gt_occupancy", "labels", "data"], labels.tobytes())),
        "oversize": b"\x00" * 2_100_000,
        "stream_mismatch": encode(camera_frame_of(frames[0], "other", 0)),
    }
    block = zenoh.CongestionControl.BLOCK  # Zenoh's default (drop) may lose these on a busy machine
    for payload in bad_inputs.values():
        session.put(keys.camera("bad"), payload, congestion_control=block)
    # straight at the registration worker too: an occupancy frame with NaN coordinates, a garbage payload
    occ = msgpack.unpackb(
        encode(OccupancyFrameMsg(stream="bad", seq=0, stamp=0, source="replay", occupancy=good.gt_occupancy)), raw=False
    )
    occ["occupancy"]["points"]["data"] = pts.tobytes()
    session.put(keys.occupancy("bad"), msgpack.packb(occ), congestion_control=block)
    session.put(keys.occupancy("bad"), b"\xc1", congestion_control=block)
    expected = ("unknown_kind", "unsupported_version", "oversize", "stream_mismatch")

    def all_in(events):
        codes = [e.code for e in events]
        return (
            codes.count("malformed") >= 2 and codes.count("invalid_message") >= 4 and all(c in codes for c in expected)
        )

    events = errors.wait_until(all_in, timeout=20.0)
    time.sleep(0.3)  # and nothing more than expected
    events = list(errors.events)
    codes = [e.code for e in events]
    assert codes.count("malformed") == 2 and codes.count("invalid_message") == 4, codes
    for code in ("unknown_kind", "unsupported_version", "oversize", "stream_mismatch"):
        assert code in codes, codes
    messages = " | ".join(e.message for e in events)
    for phrase in ("telepathy", "newer", "bytes", "non-finite", "labels out of range", "exceeds the limit"):
        assert phrase in messages, phrase
    assert {e.worker.split("-")[0] for e in events} == {"inference", "registration"}

    # a tile that does not exist: a query error reply naming it, and an error event
    replies = list(session.get(keys.map_tile("bad", 99, 99), timeout=5.0))
    assert len(replies) == 1 and replies[0].err is not None
    err = decode(replies[0].err.payload.to_bytes(), ErrorEvent)
    assert err.code == "tile_not_found" and "99,99" in err.message

    # then a good scene: every pose, equal to the offline run
    with OccVOClient(service.endpoint, "bad", session=session) as client:
        client.reset()
        got = np.array([client.step(f).matrix() for f in frames])
        vo = offline(frames)
        assert np.abs(got - vo.poses).max() <= 1e-9
        info_before = client.map_info()
        traj_before = client.trajectory().poses.to_numpy()
        # bad input after good: reported, and every pose and tile is kept
        session.put(keys.camera("bad"), bad_inputs["nan"], congestion_control=block)
        session.put(keys.occupancy("bad"), b"\xc1", congestion_control=block)
        with pytest.raises(ServiceError, match="tile_not_found"):
            client.tile(-50, -50)
        errors.wait(len(bad_inputs) + 2 + 1 + 3)
        time.sleep(0.2)
        assert client.map_info() == info_before
        assert np.array_equal(client.trajectory().poses.to_numpy(), traj_before)
        assert client.pose_latest().seq == n - 1
    counters = {h.role: h.counters for h in OccVOClient(service.endpoint, "bad", session=session).stats()}
    assert counters["inference"]["errors"] >= len(bad_inputs) and counters["registration"]["errors"] >= 2
    assert counters["registration"]["frames_out"] >= n
    session.close()


def test_recorded_occupancy_no_reader_accepts_is_the_inference_workers_error_and_is_not_forwarded(service):
    """The replay source publishes a frame's recorded occupancy as its own output: a label out of range or a voxel
    twice is refused there by name, and no occupancy frame goes on that its readers would refuse."""
    from occvo_core.frame import OccupancyFrame
    from occvo_core.grid import OCC3D_GRID

    session = open_session(service.endpoint)
    errors = ErrorLog(session, "recbad")
    errors.make_live(session, keys.camera("recbad"))
    forwarded = []
    sub = session.declare_subscriber(keys.occupancy("recbad"), lambda s: forwarded.append(s.payload.to_bytes()))
    cells = np.stack(np.unravel_index(np.arange(0, 64_000, 97), OCC3D_GRID.shape), axis=1)
    good = msgpack.unpackb(
        encode(
            camera_frame_of(
                OccupancyFrame(OCC3D_GRID.centres_of(cells), np.full(len(cells), 4, np.uint8)), "recbad", 0, exact=False
            )
        ),
        raw=False,
    )
    occ = good["gt_occupancy"]
    labels = np.full(len(cells), 4, np.uint8)
    labels[3] = 130
    voxels = np.frombuffer(occ["voxels"]["data"], np.uint8).reshape(-1, 3).copy()
    voxels[-5:] = voxels[:5]
    bad_label = {**good, "gt_occupancy": {**occ, "labels": {**occ["labels"], "data": labels.tobytes()}}}
    bad_twice = {**good, "gt_occupancy": {**occ, "voxels": {**occ["voxels"], "data": voxels.tobytes()}}}
    block = zenoh.CongestionControl.BLOCK
    for msg in (bad_label, bad_twice):
        session.put(keys.camera("recbad"), msgpack.packb(msg, use_bin_type=True), congestion_control=block)
    events = errors.wait(2, timeout=20.0)
    time.sleep(0.3)  # and nothing after them
    assert [(e.worker.split("-")[0], e.code) for e in errors.events] == [("inference", "invalid_message")] * 2, events
    assert "labels out of range 0..17: max 130" in events[0].message and "5 duplicate voxels" in events[1].message
    assert forwarded == []
    sub.undeclare()
    session.close()


@needs_data
def test_sequence_gaps_and_steps_back_are_reported(service):
    s = scene()
    session = open_session(service.endpoint)
    errors = ErrorLog(session, "seqs")
    errors.make_live(session, keys.camera("seqs"))
    with OccVOClient(service.endpoint, "seqs", session=session) as client:

        def send(i, seq):
            session.put(
                keys.camera("seqs"),
                encode(camera_frame_of(s[i], "seqs", seq)),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

        send(0, 0)
        send(1, 1)
        send(3, 3)  # seq 2 missing: a jump, held until seq 4 confirms it
        send(4, 4)
        assert client.wait_pose(4).seq == 4
        send(2, 2)  # arrives late: out of order, dropped
        events = errors.wait(4)
        codes = {e.code: e for e in events}
        assert "missing seq 2..2" in codes["missing_seq"].message and codes["out_of_order"].seq == 2
        assert "held until seq 4" in codes["seq_held"].message
        time.sleep(0.3)
        assert sorted(client.poses) == [0, 1, 3, 4]
    session.close()


@needs_data
def test_four_streams_keep_their_trajectories_apart(service):
    runs = {"s0": ("scene-0101", 0), "s1": ("scene-0268", 0), "s2": ("scene-0101", 20), "s3": ("scene-0268", 20)}
    n = 4
    frames = {k: [scene(name)[start + i] for i in range(n)] for k, (name, start) in runs.items()}
    got = {}

    def drive(stream):
        with OccVOClient(service.endpoint, stream) as c:
            c.reset()
            for f in frames[stream]:
                c.publish(f)
            got[stream] = np.array([c.wait_pose(i).matrix() for i in range(n)])
            got[stream + "/map"] = c.map_info()

    threads = [threading.Thread(target=drive, args=(k,)) for k in runs]
    for t in threads:
        t.start()
    for t in threads:
        t.join(120)
    for k in runs:
        vo = offline(frames[k])
        assert np.abs(got[k] - vo.poses).max() <= 1e-9, k
    assert len({round(float(got[k][-1][0, 3]), 6) for k in runs}) == 4  # four different motions


@needs_data
def test_latest_policy_drops_oldest_and_counts():
    s = scene()
    with InProcessService(policy="latest", queue_size=1) as svc:
        session = open_session(svc.endpoint)
        errors = ErrorLog(session, "live")
        errors.make_live(session, keys.camera("live"))
        # no resends: under `latest` a dropped frame is meant to stay dropped, and a resend would be dropped and counted again
        with OccVOClient(svc.endpoint, "live", session=session, resend_after=None) as c:
            c.reset()
            for i in range(6):
                c.publish(s[i])
            c.wait_pose(5, timeout=60)
            time.sleep(0.2)
            delivered = sorted(c.poses)
        stats = {h.role: h for h in c.stats()}
        drops = stats["registration"].counters["drops"] + stats["inference"].counters["drops"]
        # the newest frame always gets through; which older ones were dropped depends on timing
        assert delivered[-1] == 5 and len(delivered) < 6
        assert drops == 6 - len(delivered)
        assert stats["registration"].stages["registration"].count == len(delivered)
        session.close()


def test_device_selection():
    import torch

    from occvo_core.errors import ConfigError
    from occvo_services.occupancy_model import select_device

    assert select_device("cpu").type == "cpu"
    assert select_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA"):
            select_device("cuda")


def test_stats_and_liveliness(service):
    with OccVOClient(service.endpoint, "x") as c:
        c.wait_for_workers(timeout=10.0)  # a just-opened session learns the routers' tokens within milliseconds
        roles = {k.split("/")[2] for k in c.workers()}
        assert roles == {"inference", "registration", "map"}
        health = c.stats()
        assert {h.role for h in health} == roles
        for h in health:
            assert {"frames_in", "frames_out", "drops", "errors"} <= set(h.counters)


def test_replay_of_a_synthetic_scene(service):
    from occvo_services.commands.replay import load_scene, replay

    scene = load_scene("synthetic:1", frames=3)
    with OccVOClient(service.endpoint, "synthetic") as c:
        out = replay(c, scene, window=2)
        assert out["poses"] == 3 and not c.errors
        assert np.abs(out["trajectory"] - offline([scene[i] for i in range(3)]).poses).max() <= 1e-9
    with pytest.raises(Exception, match="synthetic:<seed>"):
        load_scene("synthetic:x")
    # the work after each pose (loop closure, map update, eviction) ran in a thread of the after-pose pool, 10 nicer
    # than the lane's thread that registers its frames: other streams' poses go first on the cores
    worker = next(w for w in service.workers if w.role == "registration")
    worker.drain()
    st, lane = worker.sessions["synthetic"], worker.lanes["synthetic"]
    after_pose = st.threads.after.native_id  # the thread that ran the stream's last work after a pose
    assert os.getpriority(os.PRIO_PROCESS, after_pose) == os.getpriority(os.PRIO_PROCESS, lane.strand.native_id) + 10
    assert st.threads.tail.done() and st.threads.tail.exception() is None


@contextlib.contextmanager
def _held_after_pose(worker, stream: str, released=None, seq: int = 1):
    """The stream's work after the pose of frame `seq` held until the yielded gate is set (held_at: it is waiting
    there); `released()` runs as it goes on. The real work runs after it; the worker is as it was on leaving."""
    gate, held_at = threading.Event(), threading.Event()
    steps = worker.ctx.after_pose

    def held(session, job):
        if session.stream == stream and job.msg.seq == seq:
            held_at.set()
            gate.wait(30)
            if released is not None:
                released()
        return steps(session, job)

    worker.ctx.after_pose = held
    try:
        yield gate, held_at
    finally:
        gate.set()
        worker.ctx.after_pose = steps


def test_a_lane_waiting_for_its_streams_after_pose_work_raises_it_to_the_lanes_priority(service):
    """Priority inheritance: niced work a pose waits for runs at the lane's priority until it ends, then is niced again."""
    from occvo_services.commands.replay import load_scene

    if os.geteuid() != 0 and resource.getrlimit(resource.RLIMIT_NICE)[0] < 20:
        pytest.skip("raising a thread's priority needs root or RLIMIT_NICE >= 20 (LimitNICE=+0)")
    worker = next(w for w in service.workers if w.role == "registration")
    scene = load_scene("synthetic:2", frames=3)
    seen = []
    # the real work, held at frame 1 until the lane is seen waiting for it; its priority once let go
    with (
        _held_after_pose(
            worker, "boost", lambda: seen.append(os.getpriority(os.PRIO_PROCESS, threading.get_native_id()))
        ) as (gate, held_at),
        OccVOClient(service.endpoint, "boost") as c,
    ):
        c.reset()
        for i in range(3):
            c.publish(scene[i])
        _wait_for(lambda: "boost" in worker.sessions and worker.lanes["boost"].strand.native_id is not None)
        st = worker.sessions["boost"]
        lane_nice = os.getpriority(os.PRIO_PROCESS, worker.lanes["boost"].strand.native_id)
        deadline = time.monotonic() + 30
        # frame 2 waits in the lane for frame 1's work (frame 0's, boosted by frame 1's lane, is over once it holds)
        while not (held_at.is_set() and st.threads.boosted) and time.monotonic() < deadline:
            time.sleep(0.01)
        gate.set()
        c.wait_pose(2, timeout=60)
    worker.drain()
    assert seen == [lane_nice]  # frame 1's work finished at the lane's priority
    thread = st.threads.after.native_id  # the pool's thread that ran it
    assert os.getpriority(os.PRIO_PROCESS, thread) == lane_nice + 10  # and was niced again
    assert not st.threads.boosted and worker.stats.snapshot()[0]["after_pose_boosted"] >= 1


def test_a_pose_is_published_while_its_work_after_the_pose_is_held(service):
    """The pose leaves as soon as registration and its commit end: its loop-closure search, map update and tiles run
    after it. Every stage on its way is in its timings, and the work after it in the worker's stats."""
    from occvo_services.commands.replay import load_scene

    worker = next(w for w in service.workers if w.role == "registration")
    scene = load_scene("synthetic:4", frames=3)
    with _held_after_pose(worker, "early") as (gate, held_at), OccVOClient(service.endpoint, "early") as c:
        c.reset()
        for i in range(3):
            c.publish(scene[i])
        pose = c.wait_pose(1, timeout=60)  # while frame 1's work after its pose is held
        assert held_at.wait(30) and not worker.sessions["early"].threads.tail.done()
        time.sleep(0.5)  # frame 2 is in the lane by now: it waits for frame 1's work
        assert 2 not in c.poses
        gate.set()
        last = c.wait_pose(2, timeout=60)
        assert not c.errors
        ref = offline([scene[i] for i in range(3)]).poses
        assert np.array_equal(np.array([c.poses[i].matrix() for i in range(3)]), ref)
    worker.drain()
    on_the_way = {"occupancy_hop", "decode", "registration_queue", "after_pose_wait", "validate", "registration"}
    assert on_the_way | {"core_wait", "camera_decode", "inference"} <= set(pose.timings_ms)
    assert last.timings_ms["after_pose_wait"] >= 0.0 and pose.timings_ms["core_wait"] >= 0.0
    _, stages = worker.stats.snapshot()
    after = {
        "complete",
        "complete.voxel_pfilter",
        "map_extract",
        "map_wait",
        "frame_after_pose",
        "tiling",
        "map_publish",
    }
    assert {"decode", "validate", "pose_encode"} | after <= set(stages) and "complete.fine_gicp" not in stages
    # the tiles were cut and sent in a thread of the map pool, at the lane's priority (it holds the GIL)
    st = worker.sessions["early"]
    map_thread = st.threads.map.native_id
    nice = os.getpriority(os.PRIO_PROCESS, worker.lanes["early"].strand.native_id)
    assert os.getpriority(os.PRIO_PROCESS, map_thread) == nice and st.threads.map_tail.done()


def _wait_for(what, timeout: float = 60.0) -> None:
    deadline = time.monotonic() + timeout
    while not what():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def _map_update_seqs(client: OccVOClient, stream: str):
    """The seqs of the stream's map updates as they arrive, and the subscriber collecting them."""
    from occvo_schemas.models import MapUpdate

    seqs: list[int] = []
    sub = client.session.declare_subscriber(
        keys.map_updates(stream), lambda s: seqs.append(decode(s.payload.to_bytes(), MapUpdate, 1 << 30).seq)
    )
    return seqs, sub


def test_frames_waiting_share_one_map_update_and_the_last_frames_tiles_are_never_held_back():
    """With frames of a stream waiting behind a frame, its tiles go out with a later frame's (every update re-sends
    whole tiles); the last frame's go out, also when what follows it is refused or a resend. The tiles served are
    the offline map's, bit for bit."""
    from occvo_services.commands.replay import load_scene

    scene = load_scene("synthetic:3", frames=6)
    with InProcessService(map_coalesce_s=60.0) as svc, OccVOClient(svc.endpoint, "batch") as c:
        worker = svc.worker("registration")
        updates, sub = _map_update_seqs(c, "batch")

        def served(frames: int) -> None:
            """The map service's tiles equal the offline map of the first `frames` frames."""
            _wait_for(lambda: c.map_info().last_seq == frames - 1)
            want = tiles_from_map(*offline([scene[i] for i in range(frames)]).map_points(), 20.0)
            got = {(t.ix, t.iy): t for t in c.region()}
            assert set(got) == set(want)
            for k, (p, l) in want.items():
                assert np.array_equal(got[k].points.to_numpy(), p) and np.array_equal(got[k].labels.to_numpy(), l)

        with _held_after_pose(worker, "batch") as (gate, held_at):
            c.reset()
            for i in range(5):
                c.publish(scene[i])
            # frame 2 in the lane waits for frame 1's work, frames 3 and 4 in its queue
            _wait_for(
                lambda: held_at.is_set() and "batch" in worker.lanes and worker.lanes["batch"].queue.q.qsize() == 2
            )
            gate.set()
            c.wait_pose(4, timeout=60)
        worker.drain()
        _wait_for(lambda: 4 in updates)
        assert updates == [0, 4]  # the first frame's (a new trajectory), then one for frames 1-4
        assert worker.stats.snapshot()[0]["map_updates_coalesced"] == 3
        served(5)

        # frame 5's work held while a resend of frame 2 comes: that is refused (answered, nothing registered), and
        # frame 5's tiles, held back for it, still go out
        with _held_after_pose(worker, "batch", seq=5) as (gate, held_at):
            c.publish(scene[5])
            assert held_at.wait(60)
            c.put_encoded(encode(camera_frame_of(scene[2], "batch", 2)))
            _wait_for(lambda: worker.sessions["batch"].entered == 7)
            gate.set()
        _wait_for(lambda: 5 in updates, timeout=10.0)  # not at the stream's retirement (idle_stream_s 30)
        assert updates == [0, 4, 5] and not c.errors
        served(6)
        sub.undeclare()


def test_a_caught_up_pose_gets_a_head_start_on_its_frames_work_after_it():
    """Caught up, a frame's work after its pose (map update, loop closure) waits pose_head_start_ms, so the pose's hops
    to its client do not share the cores with that work's kernels; the stream's next frame lets it go at once."""
    from occvo_services.commands.replay import load_scene

    scene = load_scene("synthetic:5", frames=2)
    with InProcessService(pose_head_start_ms=30_000.0) as svc, OccVOClient(svc.endpoint, "lead") as c:
        worker = svc.worker("registration")
        updates, sub = _map_update_seqs(c, "lead")
        c.reset()
        c.step(scene[0])
        time.sleep(1.0)
        assert not worker.sessions["lead"].threads.tail.done() and updates == []  # frame 0's work still waits
        c.publish(scene[1])
        c.wait_pose(1, timeout=10.0)  # frame 1 let it go: no 30 s wait
        _wait_for(lambda: 0 in updates, timeout=10.0)
        assert updates == [0]  # frame 1's work waits in turn
        worker.drain()  # ends every head start
        _wait_for(lambda: 1 in updates, timeout=10.0)
        assert not c.errors
        ref = offline([scene[i] for i in range(2)]).poses
        assert np.array_equal(np.array([c.poses[i].matrix() for i in range(2)]), ref)
        sub.undeclare()


def test_a_caught_up_poses_kernel_team_leaves_it_the_cores(tmp_path):
    """Caught up, once a frame's kernels are done, the registration worker lowers the OpenMP threads of its kernel
    team (they spin for ms after a kernel) to niceness 19, so the pose's commit and hops take the cores; the team
    thread itself keeps its priority (the threads come back before the next kernels: test_os_tuning)."""
    from occvo_services.commands.replay import load_scene
    from occvo_services.local import LocalService
    from occvo_services.os_tuning import may_raise_to

    if (os.cpu_count() or 1) < 2 or not may_raise_to(0):
        pytest.skip("one core, or no right to raise a thread's priority back (CAP_SYS_NICE or RLIMIT_NICE)")
    config = tmp_path / "registration.json5"
    config.write_text("{kernel_threads: 2, pose_head_start_ms: 30000}")  # the team, no kernels after the pose
    scene = load_scene("synthetic:5", frames=2)
    with (
        LocalService(quiet=True, worker_args={"registration": ["--config", str(config)]}) as svc,
        OccVOClient(svc.endpoint, "lead") as c,
    ):
        c.reset()
        c.step(scene[0])
        c.step(scene[1])
        task = Path(f"/proc/{svc.procs['registration'].pid}/task")
        team = sorted(int(t.name) for t in task.iterdir() if (t / "comm").read_text().strip() == "kernels_0")
        nice = [os.getpriority(os.PRIO_PROCESS, t) for t in team]
        assert len(team) >= 2 and nice[0] == 0 and set(nice[1:]) == {19}, nice  # the team thread came first


def test_kernel_threads_0_shares_the_cores_between_the_streams_registering():
    from occvo_core.free_cores import FREE_CORES
    from occvo_services.registration.scheduling import CORES, Scheduler

    free = FREE_CORES.threads(CORES)  # other processes, other shards among them, seen through the counters
    assert 1 <= Scheduler.fair_threads(1) <= CORES  # alone: every free core
    assert Scheduler.fair_threads(8) <= max(1, max(free, FREE_CORES.threads(CORES)) // 8)


def test_worker_process_memory_settings_and_thread_names():
    """glibc takes the workers' malloc settings, and a lane's OS thread is named after its stream (what `top -H`
    shows)."""
    from occvo_services.os_tuning import large_blocks_from_mmap, name_os_thread

    assert large_blocks_from_mmap()  # both mallopt calls accepted (glibc here)
    seen = []
    t = threading.Thread(
        target=lambda: (
            name_os_thread("lane-car7"),
            seen.append(Path(f"/proc/self/task/{threading.get_native_id()}/comm").read_text().strip()),
        )
    )
    t.start()
    t.join()
    assert seen == ["lane-car7"]
