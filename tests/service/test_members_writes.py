"""Placement "members" on a real PostgreSQL store: every write is fenced (a members store refuses a write without a
lease's epoch, `delete_stream` included), lease rows of streams that never stored a frame are deleted, and a flood of
puts that do not decode makes no store look-up and no lease row (the owner is decided only for a decoded frame)."""

from __future__ import annotations

import time

import numpy as np
import pytest
import zenoh
from offline import offline

from occvo_services.sessions import free_port, open_router, open_session
from occvo_services.store.blobs import pack_frame
from occvo_services.store.errors import FencedError
from occvo_services.store.factory import open_store


def _commit(store, stream: str, frame, **fence) -> None:
    store.commit_frame(stream, 0, 0.0, b"d" * 16, "ok", np.eye(4), pack_frame(frame), new_trajectory=True, **fence)


def test_a_members_store_refuses_every_unfenced_write(pg_url, scene):
    store = open_store(pg_url, fenced_only=True)
    try:
        with pytest.raises(FencedError, match="without a lease"):
            _commit(store, "car", scene[0])
        epoch = store.acquire("car", "w1", 30.0)
        _commit(store, "car", scene[0], epoch=epoch)
        with pytest.raises(FencedError):
            store.finish_frame("car", 0, np.eye(4))
        with pytest.raises(FencedError):
            store.write_snapshot("car", 0, b"state")
        with pytest.raises(FencedError):
            store.delete_stream("car")
        with pytest.raises(FencedError):
            store.delete_stream("car", epoch=epoch + 1)
        assert [p.seq for p in store.poses("car")] == [0]
        assert store.delete_stream("car", epoch=epoch) == 1 and store.poses("car") == [] and store.leases() == []
    finally:
        store.close()


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_leases_of_streams_that_stored_nothing_are_deleted(backend, tmp_path, request, scene):
    """w1's rows of streams without a frame go but those it serves; another owner's expired or released ones go
    too (a worker gone for good); a live owner's stay, and so does every stored stream's."""
    store = open_store(str(tmp_path / "s.sqlite") if backend == "sqlite" else request.getfixturevalue("pg_url"))
    try:
        for stream in ("stored", "empty", "serving", "others"):
            store.acquire(stream, "w2" if stream == "others" else "w1", 30.0)
        store.acquire("gone", "w3", 0.001)
        store.acquire("released", "w2", 30.0)
        store.release("released", "w2")
        _commit(store, "stored", scene[0])
        time.sleep(0.05)
        assert store.drop_unused_leases("w1", ["serving"]) == 3
        assert sorted(lease.stream for lease in store.leases()) == ["others", "serving", "stored"]
    finally:
        store.close()


def test_puts_that_do_not_decode_make_no_lease_row(pg_url):
    from occvo_services.registration_worker import RegistrationWorker
    from occvo_services.runtime import WorkerConfig

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    cfg = WorkerConfig(connect=endpoint, worker_id="reg-m", store_url=pg_url, placement="members", warm_up=False)
    reg = RegistrationWorker(cfg).start()
    session, store = open_session(endpoint), open_store(pg_url)
    try:
        n = 500
        for i in range(n):
            session.put(f"occvo/flood{i}/occupancy", b"x", congestion_control=zenoh.CongestionControl.BLOCK)
        deadline = time.monotonic() + 60
        while reg.stats.snapshot()[0].get("frames_in", 0) < n and time.monotonic() < deadline:
            time.sleep(0.05)
        assert reg.stats.snapshot()[0]["frames_in"] == n
        assert store.leases() == [] and store.streams() == []
    finally:
        session.close()
        store.close()
        reg.stop()
        router.close()


def test_a_client_over_its_stream_share_makes_no_placement_and_no_lease_row(pg_url):
    """Placement members, max_streams_per_client=2: one client opens 12 streams with valid frames. Its streams
    beyond 2 are refused before their placement (stream_limit, one event each): no placement decision, no store
    look-up, no lease row for them; a legitimate stream beside it gets every pose, equal to an offline run."""
    from occvo_services.client import OccVOClient
    from occvo_services.commands.replay import load_scene
    from occvo_services.inference_worker import InferenceWorker
    from occvo_services.registration_worker import RegistrationWorker
    from occvo_services.runtime import WorkerConfig

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    common = {"connect": endpoint, "log_level": "WARNING", "warm_up": False}
    # lease_s 300: no renewal pass (lease_s / 3) deletes an unused lease row while the test looks
    reg = RegistrationWorker(
        WorkerConfig(
            **common, worker_id="reg-m", store_url=pg_url, placement="members", lease_s=300.0, max_streams_per_client=2
        )
    ).start()
    inf = InferenceWorker(WorkerConfig(**common, worker_id="inf")).start()
    flooder, store = open_session(endpoint), open_store(pg_url)
    frames = load_scene("synthetic:6", frames=6)
    n = 12
    grabbers = [OccVOClient(endpoint, f"grab{i}", session=flooder, resend_after=None) for i in range(n)]
    try:
        for c in grabbers:
            c.reset()
            c.publish(frames[0])
        deadline = time.monotonic() + 120
        while sum(bool(c.errors) or 0 in c.poses for c in grabbers) < n and time.monotonic() < deadline:
            time.sleep(0.05)
        refused = [c for c in grabbers if c.errors]
        assert len(refused) == n - 2 and all(c.errors[0].code == "stream_limit" for c in refused)
        assert "max_streams_per_client=2" in refused[0].errors[0].message
        assert len([c for c in grabbers if 0 in c.poses]) == 2
        grabbed = sorted(c.stream for c in grabbers if 0 in c.poses)
        assert sorted(lease.stream for lease in store.leases()) == grabbed  # none of the refused streams'
        stats = reg.stats.snapshot()[0]
        assert stats["frames_placed"] == 2 and stats["frames_refused_before_placement"] == n - 2

        with OccVOClient(endpoint, "legit") as legit:
            legit.reset()
            got = [legit.step(f) for f in frames]
        vo = offline(frames)
        assert np.array_equal(np.array([p.matrix() for p in got]), vo.poses) and not legit.errors
        assert sorted(lease.stream for lease in store.leases()) == sorted([*grabbed, "legit"])
    finally:
        for c in grabbers:
            c.close()
        flooder.close()
        store.close()
        inf.stop()
        reg.stop()
        router.close()
