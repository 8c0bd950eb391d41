"""The shipped access control (deploy/acl/router.json5) against every spoof the issue found on an open router: the
pipeline's workers run as their users, a camera user drives a stream, and a camera or viewer session then tries a fake
map update, occupancy frame, pose, error event, queryable, liveliness token, and a frame on another camera user's
stream. Each is refused: nothing reaches the workers or the clients, the stream's map and trajectory are unchanged.
Each check has a positive control (the legitimate message on the same key arrives), so it cannot pass by accident.
Last, slot grabbers as logins: four camera users at their stream limit, a fifth user's stream gets every pose."""

from __future__ import annotations

import json
import os
import time
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import decode, encode
from occvo_schemas.models import (
    Array,
    ErrorEvent,
    MapTile,
    MapUpdate,
    OccupancyFrameMsg,
    PoseEstimate,
)
from occvo_services.client import OccVOClient, camera_frame_of
from occvo_services.router import router_config
from occvo_services.runtime import WorkerConfig
from occvo_services.sessions import ZENOH_CONFIG_ENV, free_port, zenoh_config

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
STREAM = "camera.car"  # user camera's prefix
SETTLE_S = 1.5  # how long a refused message is waited for


def _session_file(tmp: Path, user: str) -> Path:
    """The user's session config: the shipped one, or camera's with the user's name (camera users beyond the file's)."""
    shipped = DEPLOY / f"acl/session-{user}.json5"
    text = (shipped if shipped.exists() else DEPLOY / "acl/session-camera.json5").read_text()
    path = tmp / f"session-{user}.json5"
    path.write_text(text.replace('user: "camera"', f'user: "{user}"').replace("CHANGE-ME", f"pw-{user}"))
    return path


def _add_cameras(rc: zenoh.Config, cameras) -> None:
    """A subject and rules for each camera user the shipped file lacks: copies of user camera's with the user's prefix,
    as router.json5 says to write them."""
    ac = json.loads(rc.get_json("access_control"))
    rules = {r["id"]: r for r in ac["rules"]}
    known = {s["id"] for s in ac["subjects"]}
    shared = [r for r in next(p for p in ac["policies"] if p["subjects"] == ["camera"])["rules"] if "camera_" not in r]
    for user in [c for c in cameras if c not in known]:
        for suffix in ("frames", "follow"):
            rule = {**rules[f"camera_{suffix}"], "id": f"{user}_{suffix}"}
            rule["key_exprs"] = [k.replace("occvo/camera.$*", f"occvo/{user}.$*") for k in rule["key_exprs"]]
            ac["rules"].append(rule)
        ac["subjects"].append({"id": user, "usernames": [user]})
        ac["policies"].append({"rules": [f"{user}_frames", f"{user}_follow", *shared], "subjects": [user]})
        next(p for p in ac["policies"] if "see_declarations" in p["rules"])["subjects"].append(user)
    rc.insert_json5("access_control", json.dumps(ac))


@contextmanager
def _acl_service(tmp: Path, cameras=("camera", "camera2"), **config):
    """The pipeline's workers (threads, `config` on each) behind the shipped ACL on loopback, each as its user: the
    endpoint, the router session, each user's session config file and the workers by role."""
    from occvo_services.inference_worker import InferenceWorker
    from occvo_services.map_service import MapService
    from occvo_services.registration_worker import RegistrationWorker

    users = ["inference", "registration", "map", *cameras, "viewer"]
    (tmp / "users.txt").write_text("".join(f"{u}:pw-{u}\n" for u in users))
    ep = f"tcp/127.0.0.1:{free_port()}"
    rc = router_config(DEPLOY / "acl/router.json5", listen=[ep])
    rc.insert_json5("transport/auth/usrpwd/dictionary_file", json.dumps(str(tmp / "users.txt")))
    _add_cameras(rc, cameras)
    router = zenoh.open(rc)
    files = {u: _session_file(tmp, u) for u in users}
    workers = []
    saved = os.environ.get(ZENOH_CONFIG_ENV)
    try:
        try:
            for cls in (MapService, RegistrationWorker, InferenceWorker):  # each worker's session as its user
                os.environ[ZENOH_CONFIG_ENV] = str(files[cls.role])
                cfg = WorkerConfig(connect=ep, worker_id=f"{cls.role}-acl", warm_up=False, log_level="ERROR", **config)
                workers.append(cls(cfg).start())
        finally:
            if saved is None:
                os.environ.pop(ZENOH_CONFIG_ENV, None)
            else:
                os.environ[ZENOH_CONFIG_ENV] = saved
        deadline = time.monotonic() + 30  # clients of this ACL get no liveliness replies (zenoh 1.10): ask the router
        while len(_alive(router, "occvo/@alive/**")) < 3 and time.monotonic() < deadline:
            time.sleep(0.1)
        yield {"endpoint": ep, "router": router, "files": files, "workers": {w.role: w for w in workers}}
    finally:
        for w in reversed(workers):
            w.stop()
        router.close()


@pytest.fixture(scope="module")
def acl(tmp_path_factory, scene):
    with _acl_service(tmp_path_factory.mktemp("acl")) as svc:
        ep = svc["endpoint"]
        sessions = {
            u: zenoh.open(zenoh_config("client", connect=ep, base=svc["files"][u]))
            for u in ("camera", "camera2", "viewer")
        }
        try:
            with OccVOClient(ep, STREAM, timeout=60, session=sessions["camera"]) as c:
                c.reset()
                poses = [c.step(f).matrix() for f in scene[:3]]
            svc["workers"]["registration"].drain()  # the last frame's map update is out
            mapper = svc["workers"]["map"]
            deadline = time.monotonic() + 10
            while mapper.store.info(STREAM) is None or mapper.store.info(STREAM).last_seq != 2:
                assert time.monotonic() < deadline, "the map service did not get the last frame's update"
                time.sleep(0.05)
            yield {**svc, "s": sessions, "poses": poses}
        finally:
            for s in sessions.values():
                s.close()


def _alive(session, selector):
    return [str(r.ok.key_expr) for r in session.liveliness().get(selector, timeout=2.0) if r.ok]


def _received(session, key, send, marker, timeout=SETTLE_S):
    """Payloads with `marker` that `session`'s subscriber on `key` gets while `send()` is called every 0.1 s."""
    got = []
    sub = session.declare_subscriber(key, lambda s: got.append(s.payload.to_bytes()))
    try:
        time.sleep(0.3)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            send()
            time.sleep(0.1)
        return [g for g in got if marker in g]
    finally:
        sub.undeclare()


def _map_info(acl):
    replies = [r for r in acl["s"]["viewer"].get(keys.map_info(STREAM), timeout=5.0) if r.ok]
    return [decode(r.ok.payload.to_bytes()) for r in replies]


def _trajectory(acl):
    replies = [r for r in acl["s"]["viewer"].get(keys.trajectory(STREAM), timeout=5.0) if r.ok]
    return [decode(r.ok.payload.to_bytes(), None, 1 << 30) for r in replies]


def test_fake_map_update_is_refused(acl):
    before = _map_info(acl)
    assert len(before) == 1 and before[0].voxel_count > 1000
    pts = np.zeros((3, 3))
    fake = encode(
        MapUpdate(
            stream=STREAM,
            seq=0,
            reset=True,
            tile_m=20.0,
            tiles=[
                MapTile(
                    stream=STREAM,
                    ix=0,
                    iy=0,
                    tile_m=20.0,
                    seq=0,
                    points=Array.from_numpy(pts),
                    labels=Array.from_numpy(np.zeros(3, np.uint8)),
                )
            ],
        )
    )
    for user in ("camera", "viewer"):
        for _ in range(5):
            acl["s"][user].put(keys.map_updates(STREAM), fake)
    time.sleep(SETTLE_S)
    after = _map_info(acl)
    assert after[0].voxel_count == before[0].voxel_count and after[0].tile_count == before[0].tile_count
    assert acl["workers"]["map"].stats.snapshot()[0]["errors"] == 0


def test_fake_occupancy_frame_is_refused(acl, scene):
    good = camera_frame_of(scene[0], STREAM, 0)
    fake = encode(OccupancyFrameMsg(stream=STREAM, seq=0, stamp=0.0, source="replay", occupancy=good.gt_occupancy))
    reg = acl["workers"]["registration"]
    n_in = reg.stats.snapshot()[0]["frames_in"]
    for user in ("camera", "camera2", "viewer"):
        acl["s"][user].put(keys.occupancy(STREAM), fake)
    time.sleep(SETTLE_S)
    assert reg.stats.snapshot()[0]["frames_in"] == n_in
    [traj] = _trajectory(acl)
    assert traj.seqs.to_numpy().tolist() == [0, 1, 2]
    assert np.array_equal(traj.poses.to_numpy(), np.array(acl["poses"]))


def test_fake_relocalised_pose_is_refused(acl, scene):
    shifted = np.eye(4)
    shifted[0, 3] = 1000.0
    fake = encode(PoseEstimate(stream=STREAM, seq=1, stamp=0.0, pose=shifted.tolist(), status="relocalised"))
    for user, observer in (("camera", "viewer"), ("viewer", "camera")):  # a session's own puts reach it locally
        got = _received(
            acl["s"][observer],
            keys.pose(STREAM),
            lambda u=user: acl["s"][u].put(keys.pose(STREAM), fake),
            b"relocalised",
        )
        assert got == [], user
    # the control: the registration worker's poses do reach the viewer
    with OccVOClient(acl["endpoint"], STREAM, timeout=30, session=acl["s"]["camera"]) as c:
        got = []
        sub = acl["s"]["viewer"].declare_subscriber(
            keys.pose(STREAM), lambda s: got.append(decode(s.payload.to_bytes(), PoseEstimate))
        )
        time.sleep(0.3)
        c._seq = 3
        c.step(scene[3])
        deadline = time.monotonic() + 10
        while not got and time.monotonic() < deadline:
            time.sleep(0.05)
        sub.undeclare()
    assert [p.seq for p in got] == [3]


def test_fake_error_event_is_refused(acl):
    fake = encode(ErrorEvent(stream=STREAM, worker="registration-acl", code="internal", message="spoofed", seq=5))
    for user, observer in (("camera", "viewer"), ("viewer", "camera")):
        got = _received(
            acl["s"][observer],
            keys.errors(STREAM),
            lambda u=user: acl["s"][u].put(keys.errors(STREAM), fake),
            b"spoofed",
        )
        assert got == [], user
    # the control: a worker's error event reaches the viewer
    got = _received(
        acl["s"]["viewer"],
        keys.errors(STREAM),
        lambda: acl["s"]["camera"].put(keys.camera(STREAM), b"\xc1"),
        b"malformed",
    )
    assert got


def test_rogue_queryable_gets_no_query(acl):
    info = _map_info(acl)[0]
    for rogue_user, asker in (
        ("viewer", "camera"),
        ("camera", "viewer"),
    ):  # a session's own queryable answers it locally
        answered = []
        rogue = acl["s"][rogue_user].declare_queryable(
            keys.map_tile(STREAM, "*", "*"),
            lambda q, seen=answered: (seen.append(1), q.reply(str(q.key_expr), b"rogue")),
        )
        try:
            time.sleep(0.5)
            for ix, iy in info.tiles[:10]:
                replies = list(acl["s"][asker].get(keys.map_tile(STREAM, ix, iy), timeout=5.0))
                assert len(replies) == 1 and replies[0].ok is not None, rogue_user
                tile = decode(replies[0].ok.payload.to_bytes(), MapTile, 1 << 30)  # the map service's, not b"rogue"
                assert (tile.ix, tile.iy) == (ix, iy)
            assert answered == [], rogue_user
        finally:
            rogue.undeclare()


def test_fake_liveliness_token_is_refused(acl):
    tokens = [
        acl["s"][u].liveliness().declare_token(keys.alive("registration", f"fake-{u}")) for u in ("camera", "viewer")
    ]
    shard = acl["s"]["camera"].liveliness().declare_token(keys.registration_shard(0, 1, "fake-shard"))
    try:
        time.sleep(SETTLE_S)
        # the router's table is what every client is told (its own clients get no liveliness replies under this ACL)
        alive, shards = _alive(acl["router"], "occvo/@alive/**"), _alive(acl["router"], "occvo/@shard/**")
        assert keys.alive("registration", "registration-acl") in alive  # the control: the real worker's token
        assert not [k for k in alive + shards if "fake" in k], alive + shards
        assert len(shards) == 1
    finally:
        for t in (*tokens, shard):
            t.undeclare()


def test_camera_cannot_reset_another_users_stream(acl, scene):
    inf = acl["workers"]["inference"]
    n_in = inf.stats.snapshot()[0]["frames_in"]
    reset = encode(camera_frame_of(scene[0], STREAM, 0))
    for _ in range(5):
        acl["s"]["camera2"].put(keys.camera(STREAM), reset)
    time.sleep(SETTLE_S)
    assert inf.stats.snapshot()[0]["frames_in"] == n_in
    [traj] = _trajectory(acl)
    assert traj.seqs.to_numpy().tolist()[:3] == [0, 1, 2]
    # camera2 may use its own streams
    with OccVOClient(acl["endpoint"], "camera2.bus", timeout=60, session=acl["s"]["camera2"]) as c:
        c.reset()
        assert c.step(scene[0]).seq == 0


def test_four_logins_at_their_stream_limit_leave_a_fifth_login_every_pose(tmp_path, scene, uninterrupted):
    """Slot grabbers under the ACL: 4 camera logins hold max_streams_per_client streams each (max_streams full);
    a fifth login's stream takes a place of theirs and gets every pose, equal to the offline run."""
    per, grabbers, legit = 2, ["camera", "camera2", "camera3", "camera4"], "camera5"
    limits = {"client_identity": "user", "max_streams": per * len(grabbers), "max_streams_per_client": per}
    with _acl_service(tmp_path, (*grabbers, legit), **limits) as svc:
        ep, roles = svc["endpoint"], (svc["workers"]["inference"], svc["workers"]["registration"])
        sessions = {u: zenoh.open(zenoh_config("client", connect=ep, base=svc["files"][u])) for u in (*grabbers, legit)}
        try:
            held = sorted((f"{u}.s{i}", u) for u in grabbers for i in range(per))
            for stream, user in held:
                frame = encode(camera_frame_of(scene[0], stream, 0))
                sessions[user].put(keys.camera(stream), frame, congestion_control=zenoh.CongestionControl.BLOCK)
            deadline = time.monotonic() + 30
            while roles[1].stats.snapshot()[0].get("frames_out", 0) < len(held):  # every grabbed stream registered
                assert time.monotonic() < deadline, roles[1].stats.snapshot()[0]
                time.sleep(0.05)
            for w in roles:  # both workers full, each stream bound to its login (the ACL's user), not to a session
                assert sorted(w.admission.owners.items()) == held, w.role
            with OccVOClient(ep, f"{legit}.car", timeout=60, session=sessions[legit]) as c:
                c.reset()
                got = [c.step(f).matrix() for f in scene[:6]]
            assert not c.errors, c.errors
            assert np.allclose(np.array(got), np.array(uninterrupted[:6]), atol=1e-9)
            deadline = time.monotonic() + 30
            for w in roles:  # its place was one grabber's stream (retired by its lane's thread)
                assert w.admission.owners[f"{legit}.car"] == legit, w.role
                while w.stats.snapshot()[0].get("streams_reclaimed", 0) < 1 and time.monotonic() < deadline:
                    time.sleep(0.05)
                assert w.stats.snapshot()[0].get("streams_reclaimed") == 1, w.role
                assert len(w.admission.owners) == len(held), w.role
        finally:
            for s in sessions.values():
                s.close()


def test_replay_starts_and_drives_as_a_camera_login(acl, tmp_path):
    """`occvo replay` as the camera login (its session config in OCCVO_ZENOH_CONFIG): it sees the workers' tokens
    (before, the ACL gave it none and it could not start) and gets every pose."""
    import subprocess
    import sys

    repo = DEPLOY.parent
    env = {**os.environ, ZENOH_CONFIG_ENV: str(acl["files"]["camera"]), "PYTHONPATH": str(repo)}
    out = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "replay", "synthetic:5", "--frames", "3", "--stream", "camera.replay",
         "--connect", acl["endpoint"], "--out", str(tmp_path / "poses.txt"), "--quiet"],
        cwd=repo, env=env, capture_output=True, text=True, timeout=180,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    assert len((tmp_path / "poses.txt").read_text().splitlines()) == 3
