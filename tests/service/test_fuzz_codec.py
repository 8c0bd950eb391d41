"""Property-based fuzzing of the msgpack codec: every message kind, valid and mutated (bytes and structure).

decode either returns a valid message or raises CodecError with a known code and a message, never anything else;
valid messages round trip exactly. Hypothesis draws the messages and a seed; each example then checks many mutants
(numpy RNG from the seed), because drawing a message costs far more than decoding one. The number of generated
messages is printed at the end of the module."""

from __future__ import annotations

import numpy as np
import pytest
from fuzz_messages import (
    COUNT,
    KINDS,
    STRATEGIES,
    check_decode,
    mutate_bytes,
    mutate_structure,
    pack,
    rng_garbage,
    rng_seeds,
    unpack,
)
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from occvo_core.grid import OCC3D_GRID
from occvo_schemas.codec import CodecError, encode
from occvo_schemas.models import (
    MESSAGES,
    SCHEMA_VERSION,
    VERSIONS,
    Array,
    MapTileQuery,
    OccupancyFrameMsg,
    PoseEstimate,
    SparseOccupancy,
    Trajectory,
)

# deterministic for CI, no .hypothesis folder left in the repo
FUZZ = dict(
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=list(HealthCheck),
    phases=[Phase.explicit, Phase.generate, Phase.shrink],
)
START = COUNT["codec"]
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy on NaN coordinates, before they are refused
BIG = 1 << 30


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=15, **FUZZ)
@given(data=st.data())
def test_valid_messages_round_trip_exactly(kind, data):
    msg = data.draw(STRATEGIES[kind]())
    raw = encode(msg, BIG)
    back = check_decode(raw, MESSAGES[kind])
    assert back == msg and encode(back, BIG) == raw
    for name in ("seqs", "stamps", "poses", "points", "labels"):  # arrays come back bit for bit
        if isinstance(getattr(msg, name, None), Array):
            assert getattr(back, name).to_numpy().tobytes() == getattr(msg, name).to_numpy().tobytes()


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=17, **FUZZ)
@given(data=st.data(), seed=rng_seeds)
def test_mutants_decode_or_raise_codec_error(kind, data, seed):
    raw = encode(data.draw(STRATEGIES[kind]()), BIG)
    rng = np.random.default_rng(seed)
    for _ in range(20):  # bytes: bit flips, overwrites, truncation, insertion, deletion, duplication
        check_decode(mutate_bytes(raw, rng))
    other = encode(data.draw(STRATEGIES[data.draw(st.sampled_from(KINDS))]()), BIG)
    cut = int(rng.integers(0, len(raw) + 1))
    check_decode(raw[:cut] + other[cut:])  # two messages spliced
    obj = unpack(raw)
    for _ in range(20):  # structure: values, types, presence, arrays, version, kind, nesting
        bad, op = mutate_structure(obj, rng)
        packed = pack(bad)
        if packed is None:
            continue
        out = check_decode(packed)
        if not isinstance(bad, dict):
            continue
        version = bad.get("schema_version")
        if op == "version" and type(version) is int and not SCHEMA_VERSION <= version <= VERSIONS[kind]:
            assert isinstance(out, CodecError) and out.code == "unsupported_version"
            assert (version > VERSIONS[kind]) == ("newer" in out.message)
        known = isinstance(bad.get("kind"), str) and bad["kind"] in MESSAGES
        if op == "kind" and not known:
            assert isinstance(out, CodecError) and out.code == "unknown_kind"
        if op == "kind" and known and bad["kind"] != kind:
            # another model's fields do not fit; a version newer than that kind's is refused before its fields
            code = "unsupported_version" if version > VERSIONS[bad["kind"]] else "invalid_message"
            assert isinstance(out, CodecError) and out.code == code


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=10, **FUZZ)
@given(data=st.data(), seed=rng_seeds)
def test_extra_missing_and_wrong_typed_fields_are_invalid_messages(kind, data, seed):
    rng = np.random.default_rng(seed)
    obj = unpack(encode(data.draw(STRATEGIES[kind]()), BIG))
    out = check_decode(pack(dict(obj, surprise=rng_garbage(rng))))
    assert isinstance(out, CodecError) and out.code == "invalid_message" and "surprise" in out.message
    required = [n for n, f in MESSAGES[kind].model_fields.items() if f.is_required()]
    if required:
        name = required[int(rng.integers(0, len(required)))]
        out = check_decode(pack({k: v for k, v in obj.items() if k != name}))
        assert isinstance(out, CodecError) and out.code == "invalid_message" and name in out.message
    for name in ("stream", "seq", "stamp", "tile_m", "pose", "worker", "occupancy", "tiles", "images"):
        if name in obj:  # values no field of these can take, not even by pydantic's lax coercion
            value = [
                {"a": 1},
                [1, 2],
                float("nan"),
                b"\xff\xfe" if name != "stream" or kind == "error_event" else "x/y",
            ][int(rng.integers(0, 4))]
            out = check_decode(pack(dict(obj, **{name: value})))
            assert isinstance(out, CodecError) and out.code == "invalid_message" and name in out.message, (name, value)


@settings(max_examples=40, **FUZZ)
@given(seed=rng_seeds, head=st.sampled_from(KINDS))
def test_random_bytes_and_random_msgpack(seed, head):
    rng = np.random.default_rng(seed)
    for _ in range(20):
        out = check_decode(rng.bytes(int(rng.integers(0, 200))))
        assert isinstance(out, CodecError)
    for _ in range(20):
        obj = rng_garbage(rng, 3)
        if isinstance(obj, dict) and rng.random() < 0.7:  # give the garbage a real head so validation is reached
            obj = dict(obj, kind=head, schema_version=SCHEMA_VERSION)
        packed = pack(obj)
        if packed is not None:
            check_decode(packed)


@pytest.mark.parametrize("kind", KINDS)
@settings(max_examples=8, **FUZZ)
@given(data=st.data())
def test_wrong_kind_for_the_key_is_unknown_kind(kind, data):
    raw = encode(data.draw(STRATEGIES[kind]()), BIG)
    other = MESSAGES[data.draw(st.sampled_from([k for k in KINDS if k != kind]))]
    out = check_decode(raw, other)
    assert isinstance(out, CodecError) and out.code == "unknown_kind" and kind in out.message


@settings(max_examples=30, **FUZZ)
@given(data=st.data())
def test_oversize_is_refused_before_parsing(data):
    raw = encode(data.draw(STRATEGIES[data.draw(st.sampled_from(KINDS))]()), BIG)
    out = check_decode(raw, max_bytes=data.draw(st.integers(0, len(raw) - 1)))
    assert isinstance(out, CodecError) and out.code == "oversize" and str(len(raw)) in out.message
    assert not isinstance(check_decode(raw, max_bytes=len(raw)), CodecError)


def test_known_crashers():
    """Payloads that once escaped decode or encode as OverflowError, or decoded into arrays that could not be read."""
    p = OCC3D_GRID.centres_of(np.array([[1, 2, 3], [4, 5, 6]]))
    occ = unpack(
        encode(
            OccupancyFrameMsg(
                stream="s",
                seq=1,
                stamp=0.5,
                source="replay",
                occupancy=SparseOccupancy.from_points(p, np.array([1, 2]), OCC3D_GRID, exact=False),
            )
        )
    )
    for grid in (
        {"voxel_size": 5e-324},
        {"voxel_size": 1e-300},
        {"lower": [-1e308] * 3, "upper": [1e308] * 3},
        {"lower": [40.0, 40.0, 5.4], "upper": [-40.0, -40.0, -1.0]},
    ):
        bad = dict(occ, occupancy=dict(occ["occupancy"], grid=dict(occ["occupancy"]["grid"], **grid)))
        out = check_decode(pack(bad))
        assert isinstance(out, CodecError) and out.code == "invalid_message" and "grid" in out.message, out
    traj = unpack(
        encode(
            Trajectory(
                stream="s",
                seqs=Array.from_numpy(np.arange(2)),
                stamps=Array.from_numpy(np.zeros(2)),
                poses=Array.from_numpy(np.zeros((2, 4, 4))),
            )
        )
    )
    for shape in (
        [2**32, 2**32],
        [0, 2**62],
        [1] * 40,
    ):  # 2**64 elements wrapped to 0 in int64; numpy refuses the others
        traj["seqs"] = {"dtype": "int64", "shape": shape, "data": b"" if 0 in shape else b"\x00" * 8}
        out = check_decode(pack(traj))
        assert isinstance(out, CodecError) and out.code == "invalid_message" and "too large" in out.message, out
    pose = PoseEstimate(stream="s", seq=0, stamp=0.0, pose=np.eye(4).tolist(), status="ok")
    with pytest.raises(CodecError) as info:
        encode(pose.model_copy(update={"seq": 2**70}))  # a valid model msgpack cannot carry
    assert info.value.code == "invalid_message" and "pose_estimate" in info.value.message
    with pytest.raises(CodecError):
        encode(MapTileQuery(stream="s", ix_min=-(2**64)))


def test_zz_count_of_generated_messages(request, capsys, record_property):
    """Runs last in this module: report (and check) how many messages the codec fuzzing generated."""
    n = COUNT["codec"] - START
    record_property("generated_messages", n)
    with capsys.disabled():
        print(f"\nfuzz codec: {n} generated messages decoded")
    ran = {i.originalname for i in request.session.items if i.module is request.module}
    if {t for t in globals() if t.startswith("test_")} <= ran:  # the whole module ran, not a -k selection
        assert n >= 8000, n
