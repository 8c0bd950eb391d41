"""Registration workers sharing the streams (WorkerConfig.shard / shards, `count: N` in `occvo up`), on real Zenoh
sessions on loopback, in this process: each stream is registered by exactly one worker, a query gets one answer,
and a stream whose worker stops and comes back continues exactly while the other shard's stream goes on."""

from __future__ import annotations

import threading
import warnings

import numpy as np
import pytest
from conftest import SERVICE_FRAMES as N  # frames of the `scene` fixture

from occvo_schemas import keys
from occvo_schemas.codec import decode
from occvo_schemas.models import ErrorEvent, Trajectory

warnings.filterwarnings("ignore", category=RuntimeWarning)


def _stream_of_shard(shard: int, shards: int = 2) -> str:
    return next(f"car{i}" for i in range(100) if keys.shard_of(f"car{i}", shards) == shard)


def test_shard_of_is_stable_and_spreads_streams():
    assert [keys.shard_of(f"load{i}", 2) for i in range(8)] == [
        0,
        0,
        0,
        0,
        1,
        1,
        1,
        1,
    ]  # CRC-32: any process, any release
    assert {keys.shard_of(f"s{i}", 3) for i in range(30)} == {0, 1, 2} and keys.shard_of("anything", 1) == 0
    assert keys.parse_registration_shard(keys.registration_shard(1, 2, "registration-1")) == (1, 2)
    assert keys.parse_registration_shard(keys.alive("registration", "registration-1")) is None


def test_a_shard_outside_the_count_is_refused():
    from occvo_core.errors import ConfigError
    from occvo_services.runtime import WorkerConfig

    with pytest.raises(ConfigError, match="shard 2 is not one of shards 0..1"):
        WorkerConfig.load(None, shard=2, shards=2)


def test_two_shards_share_the_streams_and_one_restarts_alone(tmp_path, scene, uninterrupted):
    from occvo_services.client import OccVOClient
    from occvo_services.inference_worker import InferenceWorker
    from occvo_services.local import wait_alive
    from occvo_services.map_service import MapService
    from occvo_services.registration_worker import RegistrationWorker
    from occvo_services.runtime import WorkerConfig
    from occvo_services.sessions import free_port, open_router, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    base = {"connect": endpoint, "log_level": "WARNING"}
    store = str(tmp_path / "occvo.sqlite")  # both shards and the map service in one file, as deployed
    reg_config = [
        WorkerConfig(**base, worker_id=f"registration-{i}", store_path=store, shard=i, shards=2) for i in (0, 1)
    ]
    others = [
        MapService(WorkerConfig(**base, worker_id="map-t", store_path=store)).start(),
        InferenceWorker(WorkerConfig(**base, worker_id="inference-t")).start(),
    ]
    regs = [RegistrationWorker(c).start() for c in reg_config]
    probe = open_session(endpoint)
    name_a, name_b = _stream_of_shard(0), _stream_of_shard(1)
    try:
        wait_alive(probe, ["registration", "inference", "map"], 20)
        with OccVOClient(endpoint, name_a) as a, OccVOClient(endpoint, name_b) as b:
            a.reset()
            b.reset()
            for i in range(4):
                assert np.array_equal(a.step(scene[i]).matrix(), uninterrupted[i])
                assert np.array_equal(b.step(scene[i]).matrix(), uninterrupted[i])
            # each worker registered its own stream only, and saw nothing of the other's
            assert set(regs[0].sessions) == {name_a} and set(regs[1].sessions) == {name_b}
            assert [r.stats.snapshot()[0]["frames_out"] for r in regs] == [4, 4]
            assert [r.stats.snapshot()[0].get("frames_in") for r in regs] == [4, 4]

            # one answer a query: the owner's; a stream nobody has gets one error, from its shard's worker
            def replies(selector):
                got = list(probe.get(selector, timeout=5.0))
                return (
                    [decode(r.ok.payload.to_bytes(), Trajectory, 1 << 30) for r in got if r.ok is not None],
                    [decode(r.err.payload.to_bytes(), ErrorEvent) for r in got if r.ok is None],
                )

            ok, err = replies(keys.trajectory(name_b))
            assert [t.stream for t in ok] == [name_b] and not err
            ok, err = replies(keys.trajectory("*"))
            assert sorted(t.stream for t in ok) == sorted([name_a, name_b]) and not err
            nobody = _stream_of_shard(1, 2) + "x"
            ok, err = replies(keys.trajectory(nobody))
            assert not ok and [e.worker for e in err] == [f"registration-{keys.shard_of(nobody, 2)}"]

            # shard 1's worker stops: stream b waits for it, stream a goes on meanwhile
            regs[1].stop()
            b_poses: list = []
            b_thread = threading.Thread(target=lambda: b_poses.extend(b.step(scene[i]).matrix() for i in range(4, N)))
            b_thread.start()
            for i in range(4, N):
                assert np.array_equal(a.step(scene[i]).matrix(), uninterrupted[i])
            assert not b_poses and b_thread.is_alive()
            regs[1] = RegistrationWorker(reg_config[1]).start()  # same shard, same store: resumes stream b
            b_thread.join(60)
            assert not b_thread.is_alive()
            assert np.array_equal(np.array(b_poses), uninterrupted[4:])
            assert b.resends == 0  # its frames waited for its worker's token: none went out to be lost
            assert regs[1].stats.snapshot()[0]["resumes"] == 1 and not b.errors and not a.errors
    finally:
        probe.close()
        for w in [*regs, *others]:
            if not w.stopping.is_set():
                w.stop()
        router.close()


def test_a_stream_moves_to_its_new_shard_through_the_store(tmp_path, scene, uninterrupted):
    """One worker, then two shards on the same store: the stream's new owner resumes it exactly."""
    from occvo_services.client import OccVOClient
    from occvo_services.inference_worker import InferenceWorker
    from occvo_services.local import wait_alive
    from occvo_services.registration_worker import RegistrationWorker
    from occvo_services.runtime import WorkerConfig
    from occvo_services.sessions import free_port, open_router, open_session

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router = open_router(endpoint)
    base = {"connect": endpoint, "log_level": "WARNING", "store_path": str(tmp_path / "occvo.sqlite")}
    workers = [
        InferenceWorker(WorkerConfig(**base, worker_id="inference-t")).start(),
        RegistrationWorker(WorkerConfig(**base, worker_id="registration-only")).start(),
    ]
    probe = open_session(endpoint)
    name = _stream_of_shard(1)
    try:
        wait_alive(probe, ["registration", "inference"], 20)
        with OccVOClient(endpoint, name) as client:
            client.reset()
            for i in range(4):
                client.step(scene[i])
            workers[1].stop()
            shards = [
                RegistrationWorker(WorkerConfig(**base, worker_id=f"registration-{i}", shard=i, shards=2)).start()
                for i in (0, 1)
            ]
            workers += shards
            got = [client.step(scene[i]).matrix() for i in range(4, N)]
            assert np.array_equal(np.array([client.poses[i].matrix() for i in range(4)] + got), uninterrupted)
            assert not shards[0].sessions and set(shards[1].sessions) == {name}
            assert shards[1].stats.snapshot()[0]["resumes"] == 1 and not client.errors
    finally:
        probe.close()
        for w in workers:
            if not w.stopping.is_set():
                w.stop()
        router.close()


def test_a_worker_config_typo_names_the_key_and_what_is_allowed(tmp_path):
    from occvo_core.errors import ConfigError
    from occvo_services.worker_config import WorkerConfig

    path = tmp_path / "worker.json5"
    path.write_text("{querue_size: 3, policy: 'newest'}")
    with pytest.raises(ConfigError) as caught:
        WorkerConfig.load(path)
    line = str(caught.value)
    assert "querue_size: unknown key (did you mean queue_size?" in line
    assert "policy: 'newest' is not allowed: input should be 'lossless' or 'latest'" in line
