"""PoseEstimate version 2 (`initialised` for a trajectory's first pose, the pose covariance) beside version 1 for the
clients built before it. A v1 client validates with a closed status list and no unknown fields, so a new value or
field in a v1 message would be refused there (checked below with the v1 model and the v1 JSON Schema as shipped);
the service therefore publishes each pose in both versions, each on its own key. Through a running service
(real Zenoh sessions): a stream's statuses are offline OccVO's frame by frame, its covariances offline register()'s,
and a v1 follower still gets every pose in the form it knows."""

from __future__ import annotations

import json
import threading

import jsonschema
import numpy as np
import pytest
from pydantic import ValidationError

from occvo_schemas import keys
from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.export import JSON_DIR, drift_earlier
from occvo_schemas.models import PoseEstimate
from occvo_schemas.pose_v1 import PoseEstimateV1, as_v1, pose_puts
from occvo_services.client import OccVOClient
from occvo_services.local import InProcessService

V1_SCHEMA = json.loads((JSON_DIR / "v1" / "pose_estimate.json").read_text())


def _pose(**kw) -> PoseEstimate:
    return PoseEstimate(**{"stream": "car", "seq": 0, "stamp": 0.5, "pose": np.eye(4).tolist(), "status": "ok", **kw})


def _v1_fields(pose: PoseEstimate) -> dict:
    return {k: v for k, v in pose.model_dump().items() if k != "covariance"} | {"schema_version": 1}


def test_a_v1_client_refuses_the_new_value_and_the_new_field():
    """What a deployed v1 client would do with each change sent as version 1: refuse it (and drop the pose)."""
    assert V1_SCHEMA["$id"] == "occvo/pose_estimate/v1" and not drift_earlier()
    assert "initialised" not in V1_SCHEMA["properties"]["status"]["enum"]
    first = _v1_fields(_pose(status="initialised"))  # the additive value, version left at 1
    with pytest.raises(ValidationError, match="status"):
        PoseEstimateV1.model_validate(first)
    with pytest.raises(jsonschema.ValidationError, match="initialised"):
        jsonschema.validate(first, V1_SCHEMA)
    extra = _v1_fields(_pose()) | {"covariance": np.eye(6).tolist()}  # the optional field, version left at 1
    with pytest.raises(ValidationError, match="covariance"):
        PoseEstimateV1.model_validate(extra)
    with pytest.raises(jsonschema.ValidationError, match="covariance"):
        jsonschema.validate(extra, V1_SCHEMA)
    # sent as version 2, a v1 build's codec refuses it by its version (schemas/codec.py), as it was built to


def test_each_version_on_its_key_and_a_v2_reader_takes_v1():
    cov = np.diag([1e-6, 2e-6, 3e-6, 1e-4, 2e-4, 3e-4])
    first = _pose(status="initialised", covariance=np.zeros((6, 6)).tolist())
    (k2, d2), (k1, d1) = pose_puts(first)
    assert (k2, k1) == ("occvo/car/pose/v2", "occvo/car/pose")
    v1 = PoseEstimateV1.model_validate(decode_raw(d1))  # as a v1 client reads it
    assert v1.status == "reinitialised" and v1.schema_version == 1
    jsonschema.validate(decode_raw(d1), V1_SCHEMA)
    assert decode(d2, PoseEstimate).status == "initialised" and decode(d2, PoseEstimate).schema_version == 2
    assert decode(d1, PoseEstimate).status == "reinitialised"  # a v2 reader takes a v1 pose (an older service's)
    later = _pose(seq=1, covariance=cov.tolist())
    assert np.array_equal(decode(encode(later), PoseEstimate).covariance, cov)
    assert as_v1(later).status == "ok" and "covariance" not in as_v1(later).model_dump()
    with pytest.raises(CodecError, match="newer than this build's 2"):
        decode(encode(_pose(schema_version=3)), PoseEstimate)
    with pytest.raises(ValidationError, match="covariance"):
        _pose(covariance=[[float("nan")] * 6] * 6)
    with pytest.raises(ValidationError, match="covariance"):
        _pose(covariance=np.eye(3).tolist())


def decode_raw(data: bytes) -> dict:
    import msgpack

    return msgpack.unpackb(data, raw=False)


@pytest.fixture(scope="module")
def service():
    with InProcessService() as svc:
        yield svc


def test_through_the_service_statuses_and_covariances_are_offline_ones(service, scene):
    """A stream's poses against offline OccVO on the same frames: status frame by frame (`initialised` first) and the
    covariance register() gives (zeros for the first frame); a v1 follower gets every pose, as v1 says it."""
    from occvo_core import OccVO

    frames = scene[:6]
    vo = OccVO()
    vo.reset()
    offline_status, offline_cov = [], []
    for f in frames:
        reg = vo.register(f)
        offline_cov.append(reg.covariance)
        offline_status.append(vo.complete(reg).status)
    assert offline_status[0] == "initialised" and offline_status[1:] == ["ok"] * 5

    with OccVOClient(service.endpoint, stream="versions") as env:
        v1_got, lock = {}, threading.Lock()

        def on_v1(sample):  # a client built before version 2: its own definition, its key
            p = PoseEstimateV1.model_validate(decode_raw(sample.payload.to_bytes()))
            with lock:
                v1_got[p.seq] = p

        sub = env.session.declare_subscriber(keys.pose_v1(env.stream), on_v1)
        try:
            env.reset()
            poses = [env.step(f) for f in frames]
            latest_v2 = env.pose_latest()
            v1_latest = [
                PoseEstimateV1.model_validate(decode_raw(r.ok.payload.to_bytes()))
                for r in env.session.get(keys.pose_latest(env.stream), timeout=5)
                if r.ok is not None
            ]
        finally:
            sub.undeclare()
    assert [p.status for p in poses] == offline_status
    assert all(p.schema_version == 2 for p in poses)
    for p, want in zip(poses, offline_cov):
        assert p.covariance is not None and np.array_equal(np.array(p.covariance), want)
    assert np.all(np.linalg.eigvalsh(np.array(poses[-1].covariance)) > 0)  # a registered pose: uncertain, not certain
    with lock:
        assert sorted(v1_got) == list(range(len(frames)))
        assert [v1_got[i].status for i in range(len(frames))] == ["reinitialised"] + ["ok"] * 5
        assert all(np.array_equal(v1_got[i].pose, poses[i].pose) for i in range(len(frames)))
    assert latest_v2.seq == len(frames) - 1 and latest_v2.covariance == poses[-1].covariance
    assert [p.seq for p in v1_latest] == [len(frames) - 1]  # a v1 client's query: v1's answer
