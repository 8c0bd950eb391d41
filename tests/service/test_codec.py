"""msgpack codec: round trips, and a typed CodecError for every kind of bad payload."""

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from occvo_core.grid import OCC3D_GRID
from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.models import (
    SCHEMA_VERSION,
    Array,
    CameraFrame,
    ErrorEvent,
    MapTile,
    OccupancyFrameMsg,
    PoseEstimate,
    SparseOccupancy,
)


def occupancy_msg(n=300, exact=True, seq=0, as_points=False):
    """as_points: the coordinates as float64 points (what a frame off the grid's pattern travels as)."""
    rng = np.random.default_rng(seq)
    cells = rng.permutation(np.prod(OCC3D_GRID.shape))[:n]  # a frame is a set of voxels: each once
    idx = np.stack(np.unravel_index(cells, OCC3D_GRID.shape), axis=1)
    pts, labels = OCC3D_GRID.centres_of(idx), rng.integers(0, 17, n).astype(np.uint8)
    if as_points:
        occ = SparseOccupancy(points=Array.from_numpy(pts), labels=Array.from_numpy(labels))
    else:
        occ = SparseOccupancy.from_points(pts, labels, OCC3D_GRID, exact=exact)
    return OccupancyFrameMsg(
        stream="s0", seq=seq, stamp=seq * 0.5, source="replay", occupancy=occ, timings_ms={"inference": 1.5}
    )


@pytest.mark.parametrize("exact", [True, False])
def test_occupancy_round_trip_is_exact(exact):
    m = occupancy_msg(exact=exact)
    back = decode(encode(m), OccupancyFrameMsg)
    assert back == m
    assert np.array_equal(back.occupancy.to_points(), m.occupancy.to_points())


def test_compact_encoding_is_small():
    assert len(encode(occupancy_msg(30000, exact=False))) < 30000 * 4 + 1000


@settings(max_examples=30, deadline=None)
@given(
    st.lists(st.floats(allow_nan=False, allow_infinity=False, width=64), min_size=0, max_size=60),
    st.sampled_from(["float64", "float32", "int64", "uint8"]),
)
def test_array_round_trip(values, dtype):
    a = np.array(values, dtype=np.float64)
    if dtype != "float64":
        a = (
            np.nan_to_num(a).clip(-1e6, 1e6).astype(dtype)
            if dtype != "uint8"
            else (np.abs(np.nan_to_num(a)) % 256).astype(np.uint8)
        )
    tile = MapTile(
        stream="s",
        ix=0,
        iy=0,
        tile_m=1.0,
        seq=0,
        points=Array.from_numpy(np.zeros((0, 3))),
        labels=Array.from_numpy(np.zeros(0, np.uint8)),
    )
    assert decode(encode(tile), MapTile) == tile
    arr = Array.from_numpy(a)
    assert np.array_equal(Array.model_validate(msgpack.unpackb(msgpack.packb(arr.model_dump()))).to_numpy(), a)


def _raw(msg) -> dict:
    return msgpack.unpackb(encode(msg), raw=False)


def _pack(d) -> bytes:
    return msgpack.packb(d, use_bin_type=True)


def _code(data, expect=None, **kw):
    with pytest.raises(CodecError) as info:
        decode(data, expect, **kw)
    return info.value


def test_malformed_payloads():
    for junk in (b"", b"\xc1", b"\x93\x01", encode(occupancy_msg())[:-7], b"hello world"):
        assert _code(junk).code == "malformed"
    assert "msgpack map" in _code(_pack([1, 2, 3])).message


def test_unknown_kind_and_wrong_kind():
    assert _code(_pack({"kind": "teleport", "schema_version": 1})).code == "unknown_kind"
    e = _code(encode(ErrorEvent(stream="s", worker="w", code="internal", message="m")), CameraFrame)
    assert e.code == "unknown_kind" and "expected camera_frame, got error_event" in e.message


def test_versions():
    d = _raw(occupancy_msg())
    d["schema_version"] = SCHEMA_VERSION + 1
    e = _code(_pack(d))
    assert e.code == "unsupported_version" and "newer" in e.message
    d["schema_version"] = 0
    assert _code(_pack(d)).code == "unsupported_version"
    del d["schema_version"]
    assert _code(_pack(d)).code == "unsupported_version"


def test_oversize_on_both_sides():
    m = occupancy_msg(5000)
    data = encode(m)
    e = _code(data, max_bytes=len(data) - 1)
    assert e.code == "oversize" and str(len(data)) in e.message
    with pytest.raises(CodecError, match="oversize"):
        encode(m, max_bytes=1000)


def test_wrong_array_size_nan_and_label_range_are_invalid_messages():
    d = _raw(occupancy_msg(as_points=True))
    d["occupancy"]["points"]["data"] = d["occupancy"]["points"]["data"][:-8]
    e = _code(_pack(d))
    assert e.code == "invalid_message" and "bytes" in e.message

    m = occupancy_msg(50, as_points=True)
    pts = m.occupancy.points.to_numpy().copy()
    pts[7] = np.nan
    d = _raw(m)
    d["occupancy"]["points"]["data"] = pts.tobytes()
    assert "non-finite" in _code(_pack(d)).message

    labels = m.occupancy.labels.to_numpy().copy()
    labels[0] = 40
    d = _raw(m)
    d["occupancy"]["labels"]["data"] = labels.tobytes()
    e = _code(_pack(d))
    assert e.code == "invalid_message" and "labels out of range" in e.message

    p = _raw(PoseEstimate(stream="s", seq=0, stamp=0, pose=np.eye(4).tolist(), status="ok"))
    p["pose"][1][1] = float("nan")
    assert "non-finite" in _code(_pack(p)).message
    p["stamp"] = "yesterday"
    assert _code(_pack(p)).code == "invalid_message"


def test_extra_fields_are_rejected():
    d = _raw(occupancy_msg())
    d["surprise"] = 1
    assert "surprise" in _code(_pack(d)).message
