"""The wire protocol as a reader in another language meets it: every message kind of a live replay (router and
workers on loopback), decoded by plain msgpack, validates against schemas/json/<kind>.json, and every put, reply
and query payload names its schema in its Zenoh encoding."""

from __future__ import annotations

import json
import threading
import time

import msgpack
import numpy as np
import pytest

from occvo_schemas import keys
from occvo_schemas.export import JSON_DIR
from occvo_schemas.models import MESSAGES
from occvo_services.client import OccVOClient
from occvo_services.local import InProcessService
from occvo_services.sessions import open_session

jsonschema = pytest.importorskip("jsonschema", reason="jsonschema is in the dev extra")
STREAM = "wire"


def _schema(kind: str) -> dict:
    return json.loads((JSON_DIR / f"{kind}.json").read_text())


def test_the_schemas_name_bytes_fields_as_msgpack_bin():
    tile = _schema("map_tile")
    assert tile["$defs"]["Array"]["properties"]["data"] == {"title": "Data", "x-msgpack-type": "bin"}
    assert tile["$id"] == "occvo/map_tile/v1"


def test_every_message_kind_of_a_live_replay_validates_and_carries_its_encoding():
    from occvo_services.commands.replay import load_scene, replay

    got: list[tuple[str, str, bytes]] = []  # (key, encoding, payload) of every put, reply and query payload
    lock = threading.Lock()

    def keep(key, sample_or_query):
        payload = sample_or_query.payload
        if payload is not None:
            with lock:
                got.append((str(key), str(sample_or_query.encoding), payload.to_bytes()))

    with InProcessService() as svc:
        watcher = open_session(svc.endpoint)
        try:
            subscriber = watcher.declare_subscriber("occvo/**", lambda s: keep(s.key_expr, s))
            with OccVOClient(svc.endpoint, STREAM) as client:
                client.wait_for_workers(timeout=30.0)
                time.sleep(0.5)  # the watcher's subscription reaches the router before the first frame
                out = replay(client, load_scene("synthetic:2", frames=4), window=2)
                assert out["poses"] == 4
                assert client.region()
                watcher.put(keys.camera(STREAM), b"\xc1")  # not msgpack: the inference worker reports an error_event
                deadline = time.monotonic() + 20.0
                while time.monotonic() < deadline and not any("/errors" in k for k, _, _ in got):
                    time.sleep(0.05)
                for selector in (
                    keys.pose_latest(STREAM),
                    keys.trajectory(STREAM),
                    keys.map_info(STREAM),
                    keys.map_tile(STREAM, 0, 0),
                    keys.stats("*"),
                ):
                    for reply in watcher.get(selector, timeout=10.0):
                        assert reply.ok is not None, selector
                        keep(reply.ok.key_expr, reply.ok)
                # the client asks the map service for a region with a MapTileQuery payload; with the map service
                # gone, the watcher's queryable is the one left on the key and sees the query as sent
                svc.worker("map").stop()
                queryable = watcher.declare_queryable(keys.map_tile(STREAM, "*", "*"), lambda q: keep(q.key_expr, q))
                time.sleep(0.5)  # the queryable reaches the router
                client.region()
                queryable.undeclare()
            subscriber.undeclare()
        finally:
            watcher.close()

    kinds: dict[str, int] = {}
    for key, encoding, payload in got:
        if payload == b"\xc1":  # the test's own garbage
            continue
        media, _, schema = encoding.partition(";")
        assert media == "application/msgpack", (key, encoding)
        message = msgpack.unpackb(payload, raw=False)  # what any msgpack library hands a reader: no pydantic
        assert schema == f"occvo/{message['kind']}/v{message['schema_version']}", (key, encoding)
        jsonschema.validate(message, _schema(message["kind"]))
        kinds[message["kind"]] = kinds.get(message["kind"], 0) + 1
    assert set(kinds) == set(MESSAGES), f"kinds seen {sorted(kinds)}"
    assert kinds["pose_estimate"] >= 4 and kinds["camera_frame"] >= 4


def test_a_schema_refuses_what_its_model_refuses():
    """The schema is not a blank cheque: a pose of the wrong shape or a string where bin belongs fails it."""
    pose = {
        "kind": "pose_estimate",
        "schema_version": 1,
        "stream": "s",
        "seq": 0,
        "stamp": 0.0,
        "pose": np.eye(4).tolist(),
        "status": "ok",
    }
    jsonschema.validate(pose, _schema("pose_estimate"))
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**pose, "status": "fine"}, _schema("pose_estimate"))
    with pytest.raises(jsonschema.ValidationError):
        jsonschema.validate({**pose, "seq": -1}, _schema("pose_estimate"))
