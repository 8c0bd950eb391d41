"""What the store records for retention (services/store/usage.py) on real SQLite files and a real PostgreSQL
server: each stream's client, bytes and last write, kept by every commit and measured again after a snapshot; the
idle streams oldest first; a SQLite file from before these columns opens and gets them."""

from __future__ import annotations

import sqlite3
import time

import pytest

from occvo_core import OccVO
from occvo_services.array_pack import pack_arrays
from occvo_services.store.blobs import frame_digest, pack_frame
from occvo_services.store.factory import open_store
from occvo_services.store.sqlite import TrajectoryStore
from occvo_services.store.usage import frame_bytes


def _commit(store, stream, vo, frame, seq, client, new=None):
    r = vo.step(frame)
    digest, blob = frame_digest(frame.points, frame.labels, frame.stamp), pack_frame(frame)
    store.commit_frame(
        stream, seq, frame.stamp, digest, r.status, r.pose, blob, new_trajectory=seq == 0 if new is None else new,
        client=client,
    )  # fmt: skip
    return frame_bytes(digest, blob)


def test_a_commit_records_the_client_its_bytes_and_its_time_and_a_snapshot_measures_them(store_url, scene):
    store = open_store(store_url)
    try:
        vo, t0 = OccVO(), time.time()
        grown = [_commit(store, "car", vo, scene[i], i, "alice") for i in range(3)]
        assert store.usage("alice") == (1, sum(grown)) and store.usage("bob") == (0, 0)
        client, n, last = store.stream_usage("car")
        assert client == "alice" and n == sum(grown) and last >= t0 - 1
        state = pack_arrays(vo.state_dict())
        assert store.write_snapshot("car", 2, state)
        measured = store.measure("car")  # the journal it covers is gone, the snapshot counts
        rows = sum(v for k, v in store.sizes("car").items() if k.endswith("_bytes"))
        assert rows <= measured < rows + 65536  # SQLite: and the rest of the snapshot's last page
        assert measured >= len(state) and store.usage("alice") == (1, measured)
        # another client's frames move the stream to it; a new trajectory counts from nothing
        g = _commit(store, "car", OccVO(), scene[0], 0, "bob", new=True)
        assert store.usage("alice") == (0, 0) and store.usage("bob") == (1, g)
    finally:
        store.close()


def test_idle_streams_are_listed_longest_idle_first_and_per_client(store_url, scene):
    store = open_store(store_url)
    try:
        for stream, client in (("a", "alice"), ("b", "bob"), ("c", "alice")):
            _commit(store, stream, OccVO(), scene[0], 0, client)
            time.sleep(0.05)
        cut = time.time()
        _commit(store, "d", OccVO(), scene[0], 0, "alice")
        assert store.idle_streams(cut) == ["a", "b", "c"]
        assert store.idle_streams(cut, "alice") == ["a", "c"]
        assert store.idle_streams(0.0) == []
        store.delete_stream("a")
        assert store.usage("alice")[0] == 2 and store.stream_usage("a") is None
    finally:
        store.close()


def test_a_store_from_before_retention_opens_and_its_streams_belong_to_no_client(tmp_path, scene):
    path = tmp_path / "old.sqlite"
    store = TrajectoryStore(path)
    _commit(store, "car", OccVO(), scene[0], 0, "alice")
    store.close()
    db = sqlite3.connect(path)  # as the release before retention left it
    db.execute("DROP INDEX streams_client")
    for column in ("client", "bytes", "last_write"):
        db.execute(f"ALTER TABLE streams DROP COLUMN {column}")
    created = db.execute("SELECT created FROM streams").fetchone()[0]
    db.commit()
    db.close()
    store = TrajectoryStore(path)
    try:
        assert store.stream_usage("car") == (None, 0, pytest.approx(created))  # its TTL runs from its creation
        assert store.usage("alice") == (0, 0) and len(store.poses("car")) == 1
        g = _commit(store, "car", OccVO(), scene[1], 1, "alice", new=False)
        assert store.usage("alice") == (1, g)
    finally:
        store.close()
