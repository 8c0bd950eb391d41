"""Streams' leases and fencing in both store backends (services/store/leases.py), on a real SQLite file and a real
PostgreSQL server: one owner at a time, expiry and takeover move the epoch on, a write under a lost lease raises
FencedError and writes nothing, also while two connections race; then the PostgreSQL store while its server is down
and after it is back."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from occvo_services.store.blobs import pack_frame
from occvo_services.store.errors import FencedError, StoreUnavailable
from occvo_services.store.factory import open_store
from occvo_services.store.protocols import TRAJECTORY_STORE

FRAME_BLOB = b"f" * 4096


def _commit(store, stream, seq, epoch=None, blob=FRAME_BLOB):
    return store.commit_frame(
        stream, seq, float(seq), bytes(16), "ok", np.eye(4) * (seq + 1), blob, new_trajectory=seq == 0, epoch=epoch
    )


def _wait_expired(store, stream, timeout=30.0):
    deadline = time.monotonic() + timeout
    while store.owner_of(stream) is not None:
        assert time.monotonic() < deadline, f"lease of {stream} never expired"
        time.sleep(0.05)


def test_one_owner_at_a_time_and_takeover_moves_the_epoch_on(store_url):
    store = open_store(store_url)
    try:
        assert store.owner_of("car") is None and store.leases() == []
        assert store.acquire("car", "w1", 30.0) == 1
        assert store.acquire("car", "w2", 30.0) is None  # held by w1
        assert store.acquire("car", "w1", 30.0) == 1 and store.owner_of("car") == "w1"  # its own: same epoch
        assert store.acquire("bus", "w2", 30.0) == 1
        assert store.renew("w1", 30.0) == ["car"] and store.renew("w2", 30.0) == ["bus"]
        # released: the next owner moves the epoch on
        assert store.release("car", "w2") is False and store.release("car", "w1") is True
        assert store.owner_of("car") is None and store.renew("w1", 30.0) == []
        assert store.acquire("car", "w2", 30.0) == 2
        # expired: taken over, epoch on; the old owner can neither renew nor take it back while it is held
        assert store.acquire("bus", "w2", 0.2) == 1
        _wait_expired(store, "bus")
        assert store.renew("w2", 30.0) == ["car"]  # bus expired: not renewed
        assert store.acquire("bus", "w1", 30.0) == 2 and store.acquire("bus", "w2", 30.0) is None
        leases = {lease.stream: lease for lease in store.leases()}
        assert (leases["bus"].owner, leases["bus"].epoch) == ("w1", 2) and leases["bus"].remaining_s > 0
        # an expired lease nobody took: its owner takes it again under the same epoch (nobody wrote meanwhile)
        assert store.acquire("van", "w1", 0.2) == 1
        _wait_expired(store, "van")
        assert store.acquire("van", "w1", 30.0) == 1
    finally:
        store.close()


def test_a_write_under_a_lost_lease_raises_and_writes_nothing(store_url, scene):
    store = open_store(store_url)
    try:
        e1 = store.acquire("car", "w1", 0.2)
        for seq in range(3):
            _commit(store, "car", seq, e1)
        store.write_snapshot("car", 2, b"state-of-w1", epoch=e1)
        _wait_expired(store, "car")
        e2 = store.acquire("car", "w2", 30.0)
        assert e2 == e1 + 1
        before = (store.record("car"), [p.seq for p in store.poses("car")], store.sizes("car"), store.snapshot("car"))
        with pytest.raises(FencedError, match=f"stream car: write under lease epoch {e1} refused.*epoch {e2}") as exc:
            _commit(store, "car", 3, e1, pack_frame(scene[3]))
        assert (exc.value.stream, exc.value.epoch, exc.value.current, exc.value.owner) == ("car", e1, e2, "w2")
        with pytest.raises(FencedError):
            _commit(store, "car", 0, e1)  # a new trajectory would drop everything: refused before that
        with pytest.raises(FencedError):
            store.finish_frame("car", 2, pose=np.zeros((4, 4)), evicted={(0, 0): {"a": np.arange(3)}}, epoch=e1)
        with pytest.raises(FencedError):
            store.write_snapshot("car", 2, b"stale", epoch=e1)
        with pytest.raises(FencedError):
            store.drop_old_snapshots("car", epoch=e1)
        after = (store.record("car"), [p.seq for p in store.poses("car")], store.sizes("car"), store.snapshot("car"))
        assert after == before and store.cold_index("car") == {} and store.pose("car", 2).status == "ok"
        # the new owner writes; unfenced writes (epoch None: one embedded worker) still go through
        _commit(store, "car", 3, e2)
        store.write_snapshot("car", 3, b"state-of-w2", epoch=e2)
        assert store.snapshot("car") == (3, b"state-of-w2") and store.record("car").last_seq == 3
        _commit(store, "car", 4)
        assert store.record("car").last_seq == 4
    finally:
        store.close()


def test_a_stale_owners_snapshot_never_replaces_the_new_owners(store_url):
    """A stale owner's snapshot would undo the new owner's journal cleanup on resume: refused, the new one kept."""
    store = open_store(store_url)
    try:
        e1 = store.acquire("car", "w1", 0.2)
        for seq in range(4):
            _commit(store, "car", seq, e1)
        _wait_expired(store, "car")
        e2 = store.acquire("car", "w2", 30.0)
        assert store.write_snapshot("car", 3, b"w2", epoch=e2)
        with pytest.raises(FencedError):
            store.write_snapshot("car", 1, b"w1", epoch=e1)
        assert store.snapshot("car") == (3, b"w2") and store.record("car").snapshot_seq == 3
    finally:
        store.close()


def test_takeover_races_a_committing_owner_on_another_connection(store_url):
    """Two connections: w1 commits frames as fast as it can under epoch 1 while w2 takes the stream over. Every w1
    commit that returned is in the store, none landed after w2's acquire returned, and the store is w2's after."""
    w1, w2 = open_store(store_url), open_store(store_url)
    try:
        e1 = w1.acquire("car", "w1", 0.5)
        committed, fenced, stop = [], [], threading.Event()

        def owner():
            seq = 0
            while not stop.is_set():
                try:
                    _commit(w1, "car", seq, e1)
                    committed.append(seq)
                    seq += 1
                except FencedError as exc:
                    fenced.append(exc)
                    time.sleep(0.01)

        t = threading.Thread(target=owner)
        t.start()
        try:
            deadline = time.monotonic() + 60
            while (e2 := w2.acquire("car", "w2", 30.0)) is None:
                assert time.monotonic() < deadline
                time.sleep(0.02)
            taken = w2.record("car").last_seq
            while len(fenced) < 3:  # w1 goes on trying, and is refused
                assert time.monotonic() < deadline
                time.sleep(0.02)
        finally:
            stop.set()
            t.join(30)
        assert e2 == e1 + 1 and committed and fenced
        assert taken == committed[-1] == w2.record("car").last_seq  # nothing of w1's after the takeover
        assert [p.seq for p in w2.poses("car")] == committed
        _commit(w2, "car", taken + 1, e2)
        assert w2.record("car").last_seq == taken + 1
    finally:
        w1.close()
        w2.close()


def test_two_connections_race_for_expired_leases_and_one_wins_each(store_url):
    a, b = open_store(store_url), open_store(store_url)
    try:
        epochs = []
        for round_ in range(15):
            got: dict[str, int | None] = {}
            start = threading.Barrier(2)

            def take(store, owner, got=got, start=start):
                start.wait()
                got[owner] = store.acquire("car", owner, 0.05)

            threads = [threading.Thread(target=take, args=(s, o)) for s, o in ((a, f"a{round_}"), (b, f"b{round_}"))]
            for t in threads:
                t.start()
            for t in threads:
                t.join(30)
            won = [e for e in got.values() if e is not None]
            assert len(got) == 2 and len(won) >= 1
            # both may win in turn when the first's 50 ms lease expired before the second asked: then epochs differ
            epochs += sorted(won)
            _wait_expired(a, "car")
        assert epochs == list(range(1, len(epochs) + 1))  # every takeover moved the epoch on by one
    finally:
        a.close()
        b.close()


def test_the_factory_picks_the_backend_by_url(tmp_path, pg_url):
    from occvo_services.store.postgres import PgTrajectoryStore
    from occvo_services.store.sqlite import TrajectoryStore
    from occvo_services.worker_config import WorkerConfig

    for spec in (tmp_path / "a.sqlite", str(tmp_path / "b.sqlite"), f"sqlite:///{tmp_path}/c.sqlite"):
        s = open_store(spec)
        assert isinstance(s, TrajectoryStore) and s.path == str(tmp_path / str(spec).rsplit("/", 1)[-1])
        assert all(isinstance(s, p) for p in TRAJECTORY_STORE)  # every method of the interfaces
        s.close()
    s = open_store(pg_url)
    assert isinstance(s, PgTrajectoryStore) and all(isinstance(s, p) for p in TRAJECTORY_STORE)
    s.close()
    assert WorkerConfig(store_path="x.sqlite").store_url == "x.sqlite"
    assert WorkerConfig(store_url=pg_url).store_path == pg_url  # the worker's earlier name reads the same
    with pytest.raises(ValueError, match="name two stores"):
        WorkerConfig(store_url=pg_url, store_path="x.sqlite")


def test_postgres_down_raises_store_unavailable_and_the_next_call_after_it_is_back_works(pg_cluster, pg_url):
    from occvo_schemas.models import MapUpdate
    from occvo_services.store.factory import open_map_store

    url = pg_url.replace("postgres@", "postgres:s3cret@")  # trust auth ignores it; the errors must not show it
    store, maps = open_store(url), open_map_store(url)
    try:
        _commit(store, "car", 0)
        maps.apply(MapUpdate(stream="car", seq=0, tile_m=20.0, tiles=[]), [])
        pg_cluster.stop()
        try:
            for call in (lambda: _commit(store, "car", 1), lambda: store.poses("car"), lambda: maps.streams()):
                with pytest.raises(StoreUnavailable) as exc:
                    call()
                assert "unreachable" in str(exc.value) and "s3cret" not in str(exc.value)
                assert pg_url.rsplit("/", 1)[-1] in str(exc.value) and "postgres:***@" in str(exc.value)
            with pytest.raises(StoreUnavailable):  # again: each call tries, none hangs
                store.acquire("car", "w1", 10.0)
            assert store.file_sizes_mb() == {}
        finally:
            pg_cluster.start()
        _commit(store, "car", 1)  # the first call after the server is back works
        assert [p.seq for p in store.poses("car")] == [0, 1] and maps.streams() == ["car"]
        # a restart between two calls (no call saw it down): the broken pooled connection is replaced at once
        pg_cluster.stop()
        pg_cluster.start()
        _commit(store, "car", 2)
        assert store.record("car").last_seq == 2 and maps.info("car").last_seq == 0
    finally:
        store.close()
        maps.close()


def test_a_store_that_cannot_be_reached_at_open_says_which(pg_cluster):
    from occvo_services.sessions import free_port

    url = f"postgresql://occvo:pw@127.0.0.1:{free_port()}/occvo"
    with pytest.raises(StoreUnavailable, match=r"trajectory store postgresql://occvo:\*\*\*@127.0.0.1:\d+/occvo "):
        open_store(url)


OWNER = """
import sys, numpy as np
from occvo_services.store.errors import FencedError
from occvo_services.store.factory import open_store
store = open_store(sys.argv[1])
epoch = store.acquire("car", "w1", float(sys.argv[2]))
seq = 0
while True:
    try:
        store.commit_frame("car", seq, float(seq), bytes(16), "ok", np.eye(4), b"f" * 4096, seq == 0, epoch=epoch)
        print("committed", seq, flush=True)
        seq += 1
    except FencedError as exc:
        print("fenced", exc, flush=True)
        break
"""


def test_a_paused_owner_writes_nothing_after_its_stream_moved(tmp_path, pg_url):
    """An owner process stopped (SIGSTOP) past its lease, perhaps inside a commit: another worker takes the stream
    (the server ends the stopped session's transaction, which held the lease row, so the takeover does not wait for
    it to wake), and once continued (SIGCONT) the old owner's next commit is refused and nothing of it lands."""
    import os
    import signal
    import subprocess
    import sys

    ttl = 1.0
    proc = subprocess.Popen(
        [sys.executable, "-c", OWNER, pg_url, str(ttl)], stdout=subprocess.PIPE, text=True, cwd=tmp_path
    )
    store = open_store(pg_url)
    try:
        lines = [proc.stdout.readline() for _ in range(5)]
        assert all(line.startswith("committed") for line in lines), lines
        os.kill(proc.pid, signal.SIGSTOP)
        _wait_expired(store, "car")
        assert store.acquire("car", "w2", 60.0) == 2
        taken = (store.record("car").last_seq, [p.seq for p in store.poses("car")])
        os.kill(proc.pid, signal.SIGCONT)
        out = proc.communicate(timeout=60)[0].splitlines()
        assert out[-1].startswith("fenced stream car: write under lease epoch 1 refused") and "epoch 2" in out[-1]
        assert (store.record("car").last_seq, [p.seq for p in store.poses("car")]) == taken
        assert taken[1] == list(range(taken[0] + 1))
    finally:
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGCONT)
            proc.kill()
            proc.wait()
        store.close()


def test_a_takeover_does_not_wait_for_a_stopped_transaction_holding_the_lease(pg_url):
    """What the server sees of an owner stopped inside a commit: a transaction holding the lease row FOR SHARE and
    saying nothing more. The takeover waits for it at most the server's idle-in-transaction timeout."""
    import psycopg

    from occvo_services.store.pg_pool import IDLE_IN_TRANSACTION_S

    store = open_store(pg_url)
    try:
        assert store.acquire("car", "w1", 0.2) == 1
        stopped = psycopg.connect(pg_url, options=f"-c idle_in_transaction_session_timeout={IDLE_IN_TRANSACTION_S}s")
        stopped.execute("SELECT epoch FROM leases WHERE stream = 'car' FOR SHARE")  # a transaction left open
        _wait_expired(store, "car")
        assert store.acquire("car", "w2", 30.0) == 2
        with pytest.raises(psycopg.errors.IdleInTransactionSessionTimeout):  # its session was ended under it
            stopped.execute("SELECT 1")
        stopped.close()
    finally:
        store.close()


def test_an_owner_paused_inside_its_commit_past_its_lease_is_refused_when_it_wakes(pg_url):
    """The owner stops right after its commit took the lease row (the pause injected once, as a SIGSTOP would): the
    server ends its session, another worker takes the stream, and the woken commit, run again on a new connection,
    is refused; nothing of it lands."""
    from occvo_services.store.pg_pool import IDLE_IN_TRANSACTION_S

    w1, w2 = open_store(pg_url), open_store(pg_url)
    try:
        e1 = w1.acquire("car", "w1", 0.5)
        _commit(w1, "car", 0, e1)
        real, paused = w1.lease_table.fence, threading.Event()

        def fence_then_pause(stream, epoch):
            check = real(stream, epoch)

            def then_pause(cur):
                check(cur)
                if not paused.is_set():
                    paused.set()
                    time.sleep(IDLE_IN_TRANSACTION_S + 1.0)

            return then_pause

        w1.lease_table.fence = fence_then_pause
        result = {}

        def owner():
            try:
                _commit(w1, "car", 1, e1)
                result["committed"] = True
            except FencedError as exc:
                result["fenced"] = exc

        t = threading.Thread(target=owner)
        t.start()
        assert paused.wait(30)
        _wait_expired(w2, "car")
        assert w2.acquire("car", "w2", 60.0) == e1 + 1  # waits for the server to end the paused transaction
        t.join(60)
        assert isinstance(result.get("fenced"), FencedError) and result["fenced"].current == e1 + 1
        assert w2.record("car").last_seq == 0 and [p.seq for p in w2.poses("car")] == [0]
    finally:
        w1.close()
        w2.close()
