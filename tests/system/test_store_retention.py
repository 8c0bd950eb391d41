"""Store retention against the service on loopback (router + workers as threads, real Zenoh, a real SQLite file or
PostgreSQL database): a client opening stream after stream is held to its store quota by one store_quota error a
refused frame while another client goes on, and what was stored stays; an idle stored stream is deleted after the
stream TTL, its map too, but never one with a live session. Small quotas and TTLs; every wait is bounded."""

from __future__ import annotations

import time

import pytest

from occvo_services.client import OccVOClient, ServiceError
from occvo_services.local import InProcessService
from occvo_services.sessions import open_session
from occvo_services.store.factory import open_map_store, open_store


def wait_for(done, timeout=60.0):
    deadline = time.monotonic() + timeout
    while not done() and time.monotonic() < deadline:
        time.sleep(0.1)
    return done()


def stored_bytes(store, stream: str) -> int:
    return sum(v for k, v in store.sizes(stream).items() if k.endswith("_bytes"))


def test_a_flooding_client_is_held_to_its_store_quota_and_others_go_on(store_url, scene):
    quota_mb = 10  # a few streams' worth (a stream's snapshot is a few MB)
    limits = {"max_store_mb_per_client": quota_mb, "idle_stream_s": 1.0}
    with InProcessService(warm_up=False, store_path=store_url, **limits) as svc:
        flood = open_session(svc.endpoint)
        answered, refused = [], []
        try:
            for i in range(12):  # one client (one session), a fresh stream each frame, as the flood does
                with OccVOClient(svc.endpoint, f"flood{i}", timeout=60, session=flood) as c:
                    try:
                        c.step(scene[0])
                        answered.append(f"flood{i}")
                    except ServiceError:
                        refused += [e for e in c.errors if e.code == "store_quota"]
            with OccVOClient(svc.endpoint, "legit", timeout=60) as c:  # another client: its own quota
                legit = [c.step(f) for f in scene[:3]]
        finally:
            flood.close()
        reg = svc.worker("registration")
        # every stream idle, snapshotted and measured
        assert wait_for(lambda: not reg.lanes and all(s.vo is None for _, s in reg.sessions_now()))
    assert answered and refused and len(legit) == 3
    assert all(f"max_store_mb_per_client={quota_mb}" in e.message and e.seq == 0 for e in refused), refused[:1]
    store = open_store(store_url)
    try:
        kept = [s for s in store.streams() if s.startswith("flood")]
        assert sorted(kept) == sorted(answered)  # nothing accepted is lost
        assert all(len(store.poses(s)) == 1 for s in kept)
        sizes = [stored_bytes(store, s) for s in kept]
        # held to its quota, which it filled: a new stream needs room for one as big as its biggest
        assert sum(sizes) <= quota_mb << 20 < sum(sizes) + 2 * max(sizes), store.sizes(kept[0])
        (client,) = {store.stream_usage(s)[0] for s in kept}
        assert store.usage(client) == (len(kept), pytest.approx(sum(sizes), rel=0.5))
    finally:
        store.close()


def test_an_idle_stream_is_deleted_after_its_ttl_with_its_map_but_not_a_live_one(store_url, scene):
    with InProcessService(warm_up=False, store_path=store_url) as svc:  # no TTL: kept
        with OccVOClient(svc.endpoint, "old", timeout=60) as c:
            c.reset()
            for f in scene[:3]:
                c.step(f)
            assert wait_for(lambda: c.map_info() is not None and c.map_info().last_seq == 2)
    maps = open_map_store(store_url)
    assert maps.info("old") is not None
    ttl = {"stream_ttl_s": 2.0, "idle_stream_s": 120.0}
    with InProcessService(warm_up=False, store_path=store_url, **ttl) as svc:
        reg = svc.worker("registration")
        with OccVOClient(svc.endpoint, "live", timeout=60) as c:
            c.reset()
            c.step(scene[0])
            # idle past its TTL: deleted, trajectory and map
            assert wait_for(lambda: reg.stats.snapshot()[0].get("streams_expired") == 1)
            assert maps.info("old") is None and reg.store.record("old") is None and reg.store.poses("old") == []
            # "live" idle past the TTL too, but its session is live (idle_stream_s): kept
            time.sleep(ttl["stream_ttl_s"] * 2)
            assert "live" in reg.lanes and len(reg.store.poses("live")) == 1
            c.step(scene[1])
    maps.close()
