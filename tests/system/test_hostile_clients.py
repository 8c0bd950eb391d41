"""A hostile or careless client against the service on loopback (router + workers as threads, real Zenoh): each
case sends what the issue found harmful, then checks that one error event names it and that a legitimate stream's
frames still give the offline poses. Counts are small and every wait is bounded; timings are in
benchmarks/hostile_clients.py, not asserted here."""

from __future__ import annotations

import threading
import time

import msgpack
import numpy as np
import pytest
import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import ErrorEvent, PoseEstimate
from occvo_services.client import OccVOClient, camera_frame_of
from occvo_services.local import InProcessService
from occvo_services.sessions import open_session

BLOCK = zenoh.CongestionControl.BLOCK
LIMITS = {
    "max_streams": 6,
    "max_streams_per_client": 2,
    "max_seq_jump": 1000,
    "idle_stream_s": 2.0,
    "error_events_per_s": 2.0,
    "error_burst": 10,
}


class Events:
    def __init__(self, session, stream="*"):
        self.items: list[ErrorEvent] = []
        self.sub = session.declare_subscriber(
            keys.errors(stream), lambda s: self.items.append(decode(s.payload.to_bytes(), ErrorEvent))
        )

    def of(self, stream=None, code=None):
        return [e for e in self.items if (stream is None or e.stream == stream) and (code is None or e.code == code)]

    def wait(self, done, timeout=20.0):
        deadline = time.monotonic() + timeout
        while not done() and time.monotonic() < deadline:
            time.sleep(0.02)
        return done()


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    store = tmp_path_factory.mktemp("store") / "occvo.sqlite"
    with InProcessService(warm_up=False, store_path=str(store), **LIMITS) as svc:
        yield svc


@pytest.fixture
def session(service):
    s = open_session(service.endpoint)
    time.sleep(0.3)
    yield s
    s.close()


def steps(client, frames, first_seq):
    client._seq = first_seq
    return [client.step(f).matrix() for f in frames]


def put_as(session, key, payload, sn=[0]):  # noqa: B006 - one counter for the module's puts
    """A put naming its session in its source info, as OccVOClient's do (the workers know a client by it)."""
    sn[0] += 1
    session.put(key, payload, congestion_control=BLOCK, source_info=zenoh.SourceInfo(session.id, sn[0]))


def raw_frame(frame, stream, seq):
    """A camera frame's msgpack with any seq (the model would refuse to build one out of range)."""
    d = msgpack.unpackb(encode(camera_frame_of(frame, stream, 0)), raw=False)
    d["seq"] = seq
    return msgpack.packb(d, use_bin_type=True)


def test_seq_beyond_int64_is_one_error_and_the_stream_goes_on(service, session, scene, uninterrupted):
    events = Events(session, "h1.seq")
    with OccVOClient(service.endpoint, "h1.seq", timeout=60, session=session) as c:
        c.reset()
        got = steps(c, scene[:2], 0)
        session.put(keys.camera("h1.seq"), raw_frame(scene[2], "h1.seq", 2**64 - 1), congestion_control=BLOCK)
        assert events.wait(lambda: events.of(code="invalid_message"))
        got += steps(c, scene[2:4], 2)
    bad = events.of(code="invalid_message")
    assert len(bad) == 1 and "seq" in bad[0].message and "9223372036854775808" in bad[0].message, bad
    assert not events.of(code="out_of_order") and not events.of(code="internal")
    assert np.allclose(np.array(got), np.array(uninterrupted[:4]), atol=1e-9)


def test_seq_jump_beyond_the_window_is_reported_and_not_adopted(service, session, scene, uninterrupted):
    events = Events(session, "h1.jump")
    with OccVOClient(service.endpoint, "h1.jump", timeout=60, session=session) as c:
        c.reset()
        got = steps(c, scene[:2], 0)
        put_as(session, keys.camera("h1.jump"), raw_frame(scene[2], "h1.jump", 1 + 5000))
        assert events.wait(lambda: events.of(code="seq_jump"))
        got += steps(c, scene[2:4], 2)  # the next real frames are not "out of order"
    jumps = events.of(code="seq_jump")
    assert len(jumps) == 1 and jumps[0].seq == 5001 and "window of 1000" in jumps[0].message
    assert not events.of(code="out_of_order") and not events.of(code="missing_seq")
    assert np.allclose(np.array(got), np.array(uninterrupted[:4]), atol=1e-9)


def test_a_jump_within_the_window_is_held_and_the_real_frames_go_on(service, session, scene, uninterrupted):
    """A stray seq within max_seq_jump (seq 99,999 under the default window) is held, not adopted: the stream's real
    next frames are registered as before, and the trajectory is the offline one."""
    events = Events(session, "h1.held")
    with OccVOClient(service.endpoint, "h1.held", timeout=60, session=session) as c:
        c.reset()
        got = steps(c, scene[:2], 0)
        put_as(session, keys.camera("h1.held"), encode(camera_frame_of(scene[5], "h1.held", 1 + 500)))
        assert events.wait(lambda: events.of(code="seq_held"))
        got += steps(c, scene[2:5], 2)
        traj = c.trajectory()
    [held] = events.of(code="seq_held")
    assert held.seq == 501 and "held until seq 502" in held.message
    assert not events.of(code="out_of_order") and not [e for e in c.errors if e.seq in range(5)]
    assert traj.seqs.to_numpy().tolist() == [0, 1, 2, 3, 4]
    assert np.array_equal(traj.poses.to_numpy(), np.array(uninterrupted[:5]))
    assert np.allclose(np.array(got), np.array(uninterrupted[:5]), atol=1e-9)


def test_a_jump_confirmed_by_its_next_frame_is_registered(service, session, scene):
    """A gap the stream goes on from (frames lost upstream): the held frame and the one confirming it both get poses."""
    events = Events(session, "h1.gap")
    with OccVOClient(service.endpoint, "h1.gap", timeout=60, session=session) as c:
        c.reset()
        steps(c, scene[:2], 0)
        for seq in (3, 4):
            put_as(session, keys.camera("h1.gap"), encode(camera_frame_of(scene[seq], "h1.gap", seq)))
        assert c.wait_pose(4).seq == 4 and c.wait_pose(3).seq == 3
        assert c.trajectory().seqs.to_numpy().tolist() == [0, 1, 3, 4]
    assert [e.seq for e in events.of(code="seq_held")] == [3]
    assert events.of(code="missing_seq") and not events.of(code="out_of_order")


def test_exact_duplicates_are_answered_with_the_stored_pose(service, session, scene, uninterrupted):
    events = Events(session, "h1.dup")
    with OccVOClient(service.endpoint, "h1.dup", timeout=60, session=session) as c:
        c.reset()
        got = []
        for i in range(4):
            seq = c.publish(scene[i])
            put_as(session, keys.camera("h1.dup"), encode(camera_frame_of(scene[i], "h1.dup", i)))
            got.append(c.wait_pose(seq).matrix())
        reg = service.worker("registration")
        deadline = time.monotonic() + 20
        while reg.stats.snapshot()[0].get("republished", 0) < 4 and time.monotonic() < deadline:
            time.sleep(0.05)
    assert not events.items and not c.errors, [(e.code, e.message) for e in events.items]
    assert np.allclose(np.array(got), np.array(uninterrupted[:4]), atol=1e-9)


def test_another_session_cannot_publish_on_a_bound_stream(service, session, scene, uninterrupted):
    """A client that publishes seq k+1 on another's stream as soon as it sees pose k: its frames are refused (the
    stream is bound to the session that opened it), with no seq in the event (the owner would take it for its own
    frame's answer); the owner gets every pose, equal to offline, and no error."""
    events = Events(session, "h1.victim")
    hostile = open_session(service.endpoint)
    stolen = [encode(camera_frame_of(scene[(i + 6) % len(scene)], "h1.victim", i)) for i in range(len(scene))]

    def preempt(sample):
        k = decode(sample.payload.to_bytes(), PoseEstimate).seq
        if k + 1 < len(stolen):
            put_as(hostile, keys.camera("h1.victim"), stolen[k + 1])  # its own session's source info
            hostile.put(keys.camera("h1.victim"), stolen[k + 1], congestion_control=BLOCK)  # and none at all

    sub = hostile.declare_subscriber(keys.pose("h1.victim"), preempt)
    try:
        time.sleep(0.3)
        with OccVOClient(service.endpoint, "h1.victim", timeout=60, session=session) as c:
            c.reset()
            got = steps(c, scene[:6], 0)
            traj = c.trajectory()
        assert events.wait(lambda: len(events.of(code="not_owner")) >= 2)
    finally:
        sub.undeclare()
        hostile.close()
    assert not [e for e in c.errors if e.seq is not None] and not events.of(code="out_of_order")
    assert all(e.seq is None and "bound to the client" in e.message for e in events.of(code="not_owner"))
    assert traj.seqs.to_numpy().tolist() == list(range(6))
    assert np.array_equal(traj.poses.to_numpy(), np.array(uninterrupted[:6]))
    assert np.allclose(np.array(got), np.array(uninterrupted[:6]), atol=1e-9)


def test_pathological_msgpack_is_refused_before_work_and_frames_keep_their_order(
    service, session, scene, uninterrupted
):
    """A 13.7 MB payload of small maps (it froze the inference worker 5.3 s) is refused by the decode limits; the
    legitimate frame sent right after it gets its pose, in order."""
    events = Events(session, "h2.msgpack")
    hostile = msgpack.packb(
        {
            "kind": "camera_frame",
            "schema_version": 1,
            "stream": "h2.msgpack",
            "x": [[{"a": 1, "b": 2} for _ in range(60000)] for _ in range(35)],
        }
    )
    assert 13_000_000 < len(hostile) < 16 * 1024 * 1024
    with OccVOClient(service.endpoint, "h2.msgpack", timeout=60, session=session) as c:
        c.reset()
        got = steps(c, scene[:1], 0)
        session.put(keys.camera("h2.msgpack"), hostile, congestion_control=BLOCK)
        got += steps(c, scene[1:3], 1)
    assert events.wait(lambda: events.of(code="malformed"))
    [bad] = events.of(code="malformed")
    assert "list and map entries" in bad.message or "max_array_len" in bad.message
    assert np.allclose(np.array(got), np.array(uninterrupted[:3]), atol=1e-9)


def test_put_over_the_transport_limit_is_not_delivered(service, session, scene, uninterrupted):
    """64 MiB on a camera key: the router's transport refuses it before reassembly (no worker sees it, so no error
    event either), and the stream's next frames get their poses."""
    inference = service.worker("inference")
    before = inference.stats.snapshot()[0]["frames_in"]
    events = Events(session, "h2.big")
    session.put(keys.camera("h2.big"), b"\x00" * (64 << 20), congestion_control=BLOCK)
    with OccVOClient(service.endpoint, "h2.big", timeout=60, session=session) as c:
        c.reset()
        got = steps(c, scene[:2], 0)
    assert np.allclose(np.array(got), np.array(uninterrupted[:2]), atol=1e-9)
    assert inference.stats.snapshot()[0]["frames_in"] - before == 2  # the 64 MiB put never reached it
    assert not events.of(code="oversize")


def test_error_events_are_rate_limited_and_keys_clipped(service, session):
    events = Events(session, "*")
    long_key = f"occvo/{'x' * 60000}/camera"
    session.put(long_key, b"\xc1", congestion_control=BLOCK)
    assert events.wait(lambda: events.of(stream="*"))
    [ev] = events.of(stream="*")
    assert len(ev.key) < 300 and "60013 chars" in ev.key
    inference = service.worker("inference")
    suppressed0 = inference.stats.snapshot()[0].get("errors_suppressed", 0)
    # one client (its own session) puts garbage on 200 distinct keys: one error budget, the client's, not one a key
    noisy = open_session(service.endpoint)
    t0 = time.monotonic()
    for i in range(200):
        put_as(noisy, keys.camera(f"h3.noisy{i}"), b"\xc1")
    assert events.wait(lambda: inference.stats.snapshot()[0].get("errors_suppressed", 0) - suppressed0 > 0)
    time.sleep(0.5)
    elapsed = time.monotonic() - t0
    noisy.close()
    sent = [e for e in events.items if e.stream.startswith("h3.noisy")]
    assert 10 <= len(sent) <= 10 + 2.0 * elapsed + 1, (len(sent), elapsed)  # a burst of 10, then 2 a second
    counters = inference.stats.snapshot()[0]
    assert counters["errors_suppressed"] - suppressed0 + len(sent) == 200


def test_streams_over_the_limits_are_refused_with_an_error_naming_the_limit(service, session, scene):
    events = Events(session, "*")
    inference = service.worker("inference")
    time.sleep(LIMITS["idle_stream_s"] + 1.0)  # the other tests' streams retired: their places are free
    assert not inference.lanes and not inference.admission.owners, dict(inference.admission.owners)
    posed: set[str] = set()
    poses = session.declare_subscriber(keys.pose("h4.$*"), lambda s: posed.add(keys.stream_of(str(s.key_expr))))
    for s in ("h4.a", "h4.b", "h4.c"):  # client h4 may have 2
        session.put(keys.camera(s), encode(camera_frame_of(scene[0], s, 0)), congestion_control=BLOCK)
    assert events.wait(lambda: events.of("h4.c", "stream_limit"))
    [ev] = events.of("h4.c", "stream_limit")
    assert "max_streams_per_client=2" in ev.message
    # a lane still inferring its frame is not taken from (its frame would be lost): h4's frames done first
    assert events.wait(lambda: posed == {"h4.a", "h4.b"}, timeout=60.0), posed
    poses.undeclare()
    # six more clients, one stream each: the worker serves 6 in all; the fifth takes a place from client h4 (two
    # streams, two more than it has), the sixth finds every client at one stream and is refused
    others = [open_session(service.endpoint) for _ in range(6)]
    for i, other in enumerate(others):
        s = f"h5x{i}.a"
        put_as(other, keys.camera(s), encode(camera_frame_of(scene[0], s, 0)))
        assert events.wait(lambda s=s: s in inference.admission.owners or events.of(s))  # sessions are not ordered
    for other in others:
        other.close()
    assert [e.stream for e in events.of(code="stream_limit")] == ["h4.c", "h5x5.a"]
    assert "max_streams=6" in events.of("h5x5.a", "stream_limit")[0].message
    assert events.wait(lambda: inference.stats.snapshot()[0].get("streams_reclaimed") == 1)
    assert not events.of("h4.a") and not events.of("h4.b")
    assert inference.stats.snapshot()[0]["streams_refused"] >= 2


def test_idle_stream_gives_back_its_lane_and_resumes_from_the_store(service, session, scene, uninterrupted):
    reg = service.worker("registration")
    time.sleep(LIMITS["idle_stream_s"] + 1.0)
    with OccVOClient(service.endpoint, "h6.idle", timeout=60, session=session) as c:
        c.reset()
        got = steps(c, scene[:3], 0)
        assert "h6.idle" in reg.lanes and reg.sessions["h6.idle"].vo is not None
        deadline = time.monotonic() + LIMITS["idle_stream_s"] + 10
        while ("h6.idle" in reg.lanes or reg.sessions["h6.idle"].vo is not None) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert "h6.idle" not in reg.lanes and reg.sessions["h6.idle"].vo is None  # threads and the OccVO given back
        assert reg.sessions["h6.idle"].threads.after is None
        time.sleep(0.5)
        assert not [t.name for t in threading.enumerate() if "h6.idle" in t.name and "resend" not in t.name]
        got += steps(c, scene[3:6], 3)  # resumed from the store
    assert np.allclose(np.array(got), np.array(uninterrupted[:6]), atol=1e-9)
    assert reg.stats.snapshot()[0]["resumes"] >= 1


def test_region_and_wildcard_queries_are_paged(tmp_path, scene):
    """A get on occvo/** is answered a page at a time (max_query_tiles); the client's region() pages through the
    whole map, equal to the tiles asked one by one."""
    with (
        InProcessService(warm_up=False, max_query_tiles=4, max_query_streams=1) as svc,
        OccVOClient(svc.endpoint, "h7.map", timeout=60) as c,
        OccVOClient(svc.endpoint, "h7.other", timeout=60) as d,
    ):
        for client in (c, d):
            client.reset()
            steps(client, scene[:2], 0)
        svc.worker("registration").drain()
        deadline = time.monotonic() + 10
        while not (svc.worker("map").store.info("h7.map") and svc.worker("map").store.info("h7.map").last_seq == 1):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        info = c.map_info()
        assert info.tile_count > 4
        replies = list(c.session.get("occvo/**", timeout=10.0))
        tiles = [r for r in replies if r.ok is not None and "/map/tile/" in str(r.ok.key_expr)]
        trajectories = [r for r in replies if r.ok is not None and str(r.ok.key_expr).endswith("/trajectory")]
        truncated = [decode(r.err.payload.to_bytes(), ErrorEvent) for r in replies if r.err is not None]
        assert len(tiles) == 4 and len(trajectories) == 1
        assert [e.code for e in truncated if e.code == "truncated"] == ["truncated"]
        region = c.region()
        assert sorted((t.ix, t.iy) for t in region) == sorted(info.tiles)
        for t in region[:3]:
            one = c.tile(t.ix, t.iy)
            assert np.array_equal(one.points.to_numpy(), t.points.to_numpy())


def test_snapshot_of_a_reset_stream_is_deleted(service, session, scene):
    reg = service.worker("registration")
    with OccVOClient(service.endpoint, "h8.reset", timeout=60, session=session) as c:
        c.reset()
        steps(c, scene[:2], 0)
        deadline = time.monotonic() + LIMITS["idle_stream_s"] + 10  # retired: its state snapshotted
        while reg.sessions["h8.reset"].vo is not None and time.monotonic() < deadline:
            time.sleep(0.1)
        old = reg.store.created("h8.reset")
        rows = reg.store.snap_db.execute("SELECT created FROM snapshots WHERE stream='h8.reset'").fetchall()
        assert rows == [(old,)]
        c.reset()
        steps(c, scene[2:3], 0)  # a new trajectory (scene[0] again would be answered as a resend)
        deadline = time.monotonic() + 10  # the snapshot writer deletes it, after what it had queued
        while (
            rows := reg.store.snap_db.execute("SELECT created FROM snapshots WHERE stream='h8.reset'").fetchall()
        ) and time.monotonic() < deadline:
            time.sleep(0.1)
    assert rows == [] and reg.store.created("h8.reset") != old, (rows, old, reg.store.created("h8.reset"))


def test_wildcard_gets_are_bounded_per_client_and_a_tile_query_is_answered(tmp_path, scene):
    """Ten threads of one client looping `occvo/**` gets: at most max_wildcard_queries (1) of them is in work at once,
    the rest get an immediate `busy` reply naming the limit, and another client's tile queries meanwhile are all
    answered with the tile (their latency is in benchmarks/hostile_clients.py)."""
    with (
        InProcessService(warm_up=False, max_queries_per_client=2, max_wildcard_queries=1) as svc,
        OccVOClient(svc.endpoint, "h9.map", timeout=60) as c,
    ):
        c.reset()
        steps(c, scene[:2], 0)
        mapper = svc.worker("map")
        deadline = time.monotonic() + 10
        while not ((info := mapper.store.info("h9.map")) and info.last_seq == 1):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        ix, iy = info.tiles[0]
        expected = c.tile(ix, iy).points.to_numpy()
        busy, peak, stop = [], [0], threading.Event()
        hammer = open_session(svc.endpoint)

        def wildcard():
            for _ in range(15):
                for r in hammer.get("occvo/**", timeout=10.0):
                    if r.err is not None and (e := decode(r.err.payload.to_bytes(), ErrorEvent)).code == "busy":
                        busy.append(e)

        def watch():
            while not stop.wait(0.001):
                peak[0] = max(peak[0], mapper.query_gates["on_tile_query"].in_work.get("*", 0))

        threads = [threading.Thread(target=wildcard) for _ in range(10)]
        watcher = threading.Thread(target=watch)
        for t in [*threads, watcher]:
            t.start()
        tiles = [c.tile(ix, iy).points.to_numpy() for _ in range(30)]
        for t in threads:
            t.join(60)
        stop.set()
        watcher.join()
        hammer.close()
        # one client's own six threads over its limit (2): the client asks again on busy, every query is answered
        mine = [
            threading.Thread(target=lambda: tiles.extend([c.tile(ix, iy).points.to_numpy() for _ in range(5)]))
            for _ in range(6)
        ]
        for t in mine:
            t.start()
        for t in mine:
            t.join(60)
    assert len(tiles) == 30 + 6 * 5
    assert all(np.array_equal(t, expected) for t in tiles)
    assert busy and "max_wildcard_queries=1" in busy[0].message and busy[0].stream == "*"
    assert peak[0] == 1
    assert mapper.stats.snapshot()[0]["queries_refused"] >= 1


def test_degenerate_frames_say_so_and_get_a_constant_velocity_pose(service, session, scene):
    """One voxel, three collinear voxels, an all-zero coordinate table: status "degenerate" (not "ok"), the pose
    the constant-velocity guess; the stream goes on, every pose equal to offline OccVO's over the same frames."""
    from occvo_core import OccVO
    from occvo_core.frame import OccupancyFrame
    from occvo_schemas.models import Array

    labels = scene[3].labels
    zero = camera_frame_of(scene[5], "h10.degenerate", 5)
    occ = zero.gt_occupancy
    zero = zero.model_copy(
        update={"gt_occupancy": occ.model_copy(update={"axes": Array.from_numpy(np.zeros(occ.axes.shape))})}
    )
    bad = [
        OccupancyFrame(scene[3].points[:1].copy(), labels[:1].copy(), index=3, stamp=scene[3].stamp),
        OccupancyFrame(np.array([[0.2, 0.2, 0.2], [1.0, 0.2, 0.2], [1.8, 0.2, 0.2]]), labels[:3].copy(), index=4),
        zero,
    ]
    offline_bad = [*bad[:2], OccupancyFrame(zero.gt_occupancy.to_points(), occ.labels.to_numpy(), 5, scene[5].stamp)]
    assert not offline_bad[2].points.any()
    vo = OccVO()
    offline = [vo.step(f) for f in [*scene[:3], *offline_bad, *scene[6:8]]]
    with OccVOClient(service.endpoint, "h10.degenerate", timeout=60, session=session) as c:
        c.reset()
        got = [c.step(f) for f in [*scene[:3], *bad, *scene[6:8]]]
    assert [p.status for p in got[3:6]] == ["degenerate"] * 3 and [r.status for r in offline[3:6]] == ["degenerate"] * 3
    assert all(p.status == "ok" for p in got[6:])
    p1, p2 = offline[1].pose, offline[2].pose
    assert np.allclose(got[3].matrix(), p2 @ np.linalg.inv(p1) @ p2, atol=1e-9)  # constant velocity
    assert np.allclose(np.array([p.matrix() for p in got]), np.array([r.pose for r in offline]), atol=1e-9)


def test_duplicate_voxels_and_more_voxels_than_the_grid_are_refused_by_name(service, session, scene):
    """A frame is a set of voxels: 1,000 copies of one voxel, or more voxels than the grid's 200x200x16 cells, get
    one error naming it before any work; the stream's next good frame is registered."""
    import msgpack

    events = Events(session, "h11.heavy")
    with OccVOClient(service.endpoint, "h11.heavy", timeout=60, session=session) as c:
        c.reset()
        c.step(scene[0])
        good = msgpack.unpackb(encode(camera_frame_of(scene[1], "h11.heavy", 1)), raw=False)
        copies = dict(good)
        occ = dict(good["gt_occupancy"])
        voxels = np.frombuffer(occ["voxels"]["data"], np.uint8).reshape(-1, 3)
        occ["voxels"] = {**occ["voxels"], "shape": [1000, 3], "data": np.repeat(voxels[:1], 1000, 0).tobytes()}
        occ["labels"] = {**occ["labels"], "shape": [1000], "data": bytes(1000)}
        copies["gt_occupancy"] = occ
        c.put_encoded(msgpack.packb(copies, use_bin_type=True))
        assert events.wait(lambda: events.of(code="invalid_message"))
        over = dict(copies)
        n = 200 * 200 * 16 + 1
        over["gt_occupancy"] = {
            **occ,
            "voxels": {**occ["voxels"], "shape": [n, 3], "data": bytes(3 * n)},
            "labels": {**occ["labels"], "shape": [n], "data": bytes(n)},
        }
        c.put_encoded(msgpack.packb(over, use_bin_type=True))
        assert events.wait(lambda: len(events.of(code="invalid_message")) == 2)
        assert c.step(scene[1]).seq == 1
    dup, big = (e.message for e in events.of(code="invalid_message"))
    assert "999 duplicate voxels" in dup and "more than the grid's 640000 cells" in big, (dup, big)


def test_a_frame_other_frames_in_work_leave_no_room_for_waits_its_turn(service, session, scene):
    """Frames of other streams in work hold the memory cap, and a frame that would fit alone comes: it is turned away
    (stream_full, flow control) and registered once they are done, never refused for good as if it were too big."""
    import threading

    from occvo_services.registration.worker import FRAME_MB_PER_VOXEL

    reg = service.worker("registration")
    with OccVOClient(service.endpoint, "h12.waits", timeout=60, session=session) as c:
        c.reset()
        steps(c, scene[:2], 0)
        cost = FRAME_MB_PER_VOXEL * len(scene[2].labels)
        assert cost > 2  # the margin below
        deadline = time.monotonic() + 60  # the frames before are given back once their handling ends
        while reg.memory.charged and time.monotonic() < deadline:
            time.sleep(0.05)
        saved, rss = reg.memory.max_rss_mb, reg.memory.rss()
        reg.memory.max_rss_mb = int(rss) + 2000
        held = reg.memory.max_rss_mb - rss - 1  # room for this frame alone, not beside the others'
        assert reg.memory.charge("others", 0, held) is None  # as other streams' frames in work are charged
        release = threading.Timer(2.0, reg.memory.discharge, (held,))
        release.start()
        try:
            assert c.step(scene[2]).seq == 2
        finally:
            release.join()
            reg.memory.max_rss_mb = saved
        assert c.turned_away >= 1 and not c.errors, (c.turned_away, c.errors)
        assert c.poses[2].status == "ok"
        assert c.trajectory().seqs.to_numpy().tolist() == [0, 1, 2]


def test_a_frame_is_charged_against_the_memory_cap_before_it_is_queued(service, session, scene):
    """A full-grid frame (every one of the 640,000 cells) on an admitted stream while the registration worker's
    resident set and that frame's cost would pass max_rss_mb: refused with one error naming the cap, nothing
    registered; the stream's next frame is registered."""
    from occvo_core.grid import OCC3D_GRID
    from occvo_schemas.models import CameraFrame, SparseOccupancy
    from occvo_services.client import ServiceError
    from occvo_services.registration.worker import FRAME_MB_PER_VOXEL

    reg = service.worker("registration")
    idx = np.indices(OCC3D_GRID.shape).reshape(3, -1).T.astype(np.uint8)
    labels = np.random.default_rng(0).integers(1, 17, len(idx)).astype(np.uint8)
    heavy = SparseOccupancy.model_validate(
        {
            "voxels": {"dtype": "uint8", "shape": [len(idx), 3], "data": idx.tobytes()},
            "labels": {"dtype": "uint8", "shape": [len(idx)], "data": labels.tobytes()},
        }
    )
    cost = FRAME_MB_PER_VOXEL * len(idx)
    with OccVOClient(service.endpoint, "h12.charged", timeout=60, session=session) as c:
        c.reset()
        steps(c, scene[:2], 0)
        saved = reg.memory.max_rss_mb
        reg.memory.max_rss_mb = int(reg.memory.rss() + reg.memory.charged + cost / 2)  # the frame does not fit
        try:
            with pytest.raises(ServiceError, match="max_rss_mb") as refused:
                c.step(CameraFrame(stream="h12.charged", seq=0, stamp=1.0, gt_occupancy=heavy))
        finally:
            reg.memory.max_rss_mb = saved
        assert refused.value.event.code == "oversize" and refused.value.event.seq == 2
        c.errors.clear()  # the refused frame's answer
        steps(c, scene[2:3], 2)  # the refused seq again, a frame that fits
        assert c.poses[2].status == "ok"
        assert c.trajectory().seqs.to_numpy().tolist() == [0, 1, 2]
    # given back once each frame's handling ends, which is after its pose went out
    deadline = time.monotonic() + 60
    while reg.memory.charged and time.monotonic() < deadline:
        time.sleep(0.05)
    assert reg.memory.charged == 0.0


def test_a_silent_queryable_and_a_querier_of_the_victims_stream_cost_it_no_answer(service, session, scene):
    """A queryable on occvo/** that never answers: the client's tile, map info, trajectory and pose queries are
    answered as before (one answer is taken as it comes; the map service's queryables are complete and the client
    asks the best match). Another session looping queries named with the victim's stream: the victim's own query
    budget is its session's, so none of its queries is refused busy."""
    held, asked = [], threading.Event()
    with OccVOClient(service.endpoint, "h13.victim", timeout=60, session=session) as c:
        c.reset()
        steps(c, scene[:2], 0)
        mapper = service.worker("map")
        deadline = time.monotonic() + 10
        while not ((info := mapper.store.info("h13.victim")) and info.last_seq == 1):
            assert time.monotonic() < deadline
            time.sleep(0.05)
        ix, iy = info.tiles[0]
        expected = (c.tile(ix, iy).points.to_numpy(), c.map_info(), c.trajectory().poses.to_numpy())

        def silent(query):
            held.append(query)  # never answered while held: the query stays open here until its timeout
            asked.set()

        rogue = open_session(service.endpoint)
        queryable = rogue.declare_queryable("occvo/**", silent)
        try:
            time.sleep(0.3)
            tile, got_info, traj, latest = c.tile(ix, iy), c.map_info(), c.trajectory(), c.pose_latest()
            assert asked.wait(5)  # the rogue was asked (trajectory and pose queries match every queryable)
            assert np.array_equal(tile.points.to_numpy(), expected[0]) and got_info == expected[1]
            assert np.array_equal(traj.poses.to_numpy(), expected[2]) and latest.seq == 1

            stop, busy_for_hostile = threading.Event(), []
            hostile = open_session(service.endpoint)

            def hammer():
                while not stop.is_set():
                    sel = keys.map_tile("h13.victim", ix, iy)
                    for r in hostile.get(sel, timeout=5.0, target=zenoh.QueryTarget.BEST_MATCHING):
                        if r.err is not None and decode(r.err.payload.to_bytes(), ErrorEvent).code == "busy":
                            busy_for_hostile.append(1)

            threads = [threading.Thread(target=hammer) for _ in range(8)]
            for t in threads:
                t.start()
            try:
                for k in range(20):  # one get each, not asked again on busy: as the victim's session
                    info = zenoh.SourceInfo(session.id, 10_000 + k)
                    best = zenoh.QueryTarget.BEST_MATCHING  # the map service's complete queryable, not the rogue
                    sel = keys.map_tile("h13.victim", ix, iy)
                    replies = list(session.get(sel, timeout=10.0, source_info=info, target=best))
                    errs = [decode(r.err.payload.to_bytes(), ErrorEvent) for r in replies if r.err is not None]
                    assert [r for r in replies if r.ok is not None] and not errs, errs
            finally:
                stop.set()
                for t in threads:
                    t.join(30)
                hostile.close()
        finally:
            queryable.undeclare()
            held.clear()
            rogue.close()
    assert busy_for_hostile  # the hostile session's budget ran out, not the victim's


def test_after_a_disk_full_spell_every_pose_is_there_and_the_map_complete(service, session, scene, uninterrupted):
    """The registration worker's store refuses writes (SQLite's own `database or disk is full`, its page count
    capped) while frames come: they get `not_stored` (not an answer), the frames after them wait, the client sends
    them again; once there is room every pose is there, equal to offline, and the map is that of a stream that never
    saw the spell."""
    reg, mapper = service.worker("registration"), service.worker("map")
    with OccVOClient(service.endpoint, "h14.ref", timeout=60, session=session) as ref:
        ref.reset()
        steps(ref, scene[:8], 0)
    db = reg.store.db
    with OccVOClient(service.endpoint, "h14.full", timeout=120, session=session, resend_after=0.5) as c:
        c.reset()
        got = steps(c, scene[:3], 0)
        assert reg.snapshots_written(60)  # no snapshot frees journal pages during the spell
        with reg.store.lock:
            # the file's free pages taken first (a commit would reuse them), then the file capped: full, made so
            free, size = (db.execute(f"PRAGMA {p}").fetchone()[0] for p in ("freelist_count", "page_size"))
            db.execute("CREATE TABLE spell_filler (b BLOB)")
            db.execute("INSERT INTO spell_filler VALUES (zeroblob(?))", (free * size,))
            pages = db.execute("PRAGMA page_count").fetchone()[0]
            db.execute(f"PRAGMA max_page_count={pages}")  # full: no page more
        try:
            for f in scene[3:6]:
                c.publish(f)
            with c._cv:
                assert c._cv.wait_for(lambda: any(e.code == "not_stored" for e in c.errors), 60)
            time.sleep(1.0)  # resends refused meanwhile (their events within the client's error budget)
        finally:
            with reg.store.lock:
                db.execute("PRAGMA max_page_count=1073741823")  # room again
                db.execute("DROP TABLE spell_filler")
        got += [c.wait_pose(seq).matrix() for seq in range(3, 6)]
        got += steps(c, scene[6:8], 6)
        traj = c.trajectory()
    assert np.allclose(np.array(got), np.array(uninterrupted[:8]), atol=1e-9)
    assert traj.seqs.to_numpy().tolist() == list(range(8))
    assert "disk is full" in next(e.message for e in c.errors if e.code == "not_stored")
    deadline = time.monotonic() + 20
    while not ((info := mapper.store.info("h14.full")) and info.last_seq == 7) and time.monotonic() < deadline:
        time.sleep(0.05)
    want = mapper.store.info("h14.ref")
    assert info.last_seq == 7 and info.tiles == want.tiles and info.voxel_count == want.voxel_count
