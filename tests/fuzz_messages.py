"""Hypothesis strategies for every occvo wire message, and mutators of their bytes and of their msgpack structure.
Shared by tests/service/test_fuzz_codec.py (in process) and tests/service/test_fuzz_workers.py (through real Zenoh workers)."""

from __future__ import annotations

import copy
import tempfile
from collections import Counter
from pathlib import Path
from typing import get_args

import msgpack
import numpy as np
from hypothesis import strategies as st
from hypothesis.configuration import set_hypothesis_home_dir
from pydantic import BaseModel

from occvo_core.grid import NUM_CLASSES, OCC3D_GRID
from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.models import (
    MESSAGES,
    Array,
    CameraFrame,
    CameraImage,
    ErrorCode,
    ErrorEvent,
    GridSpecModel,
    MapInfo,
    MapTile,
    MapTileQuery,
    MapUpdate,
    OccupancyFrameMsg,
    PoseEstimate,
    SparseOccupancy,
    StageStats,
    Trajectory,
    WorkerHealth,
)

# hypothesis keeps caches (and patches of failing examples) in its home dir: keep them out of the repository
set_hypothesis_home_dir(Path(tempfile.gettempdir()) / "occvo-hypothesis")
ERROR_CODES = set(get_args(ErrorCode))
KINDS = sorted(MESSAGES)
COUNT: Counter = Counter()  # generated messages by test area, reported at the end of each module

# ------------------------------------------------------------------ valid messages

STREAM_CHARS = "abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-."
streams = st.text(STREAM_CHARS, min_size=1, max_size=64)
finite = st.floats(allow_nan=False, allow_infinity=False)
small_finite = st.floats(-1e6, 1e6, allow_nan=False)
i64 = st.integers(-(2**63), 2**63 - 1)
seqs = st.integers(0, 2**63 - 1) | st.integers(0, 50)
timings = st.dictionaries(st.text(max_size=20), finite, max_size=4)
rng_seeds = st.integers(0, 2**32 - 1)


@st.composite
def grids(draw) -> GridSpecModel:
    if draw(st.booleans()):
        return GridSpecModel()
    vs = draw(st.floats(0.05, 2.0))
    lower = [draw(st.floats(-100, 100)) for _ in range(3)]
    shape = [draw(st.integers(1, 256)) for _ in range(3)]
    upper = [lo + n * vs for lo, n in zip(lower, shape)]
    return GridSpecModel(lower=tuple(lower), upper=tuple(upper), voxel_size=vs)


@st.composite
def occupancies(draw, max_n: int = 64, grid=None) -> SparseOccupancy:
    g = (draw(grid) if grid is not None else draw(grids())).to_grid()
    rng = np.random.default_rng(draw(rng_seeds))
    n = draw(st.integers(0, max_n))
    shape = np.array([max(1, s) for s in g.shape])
    idx = rng.integers(0, shape, size=(n, 3))
    idx = np.minimum(idx, np.array(g.shape) - 1)
    labels = rng.integers(0, NUM_CLASSES, n).astype(np.uint8)
    idx, first = np.unique(idx, axis=0, return_index=True)  # a frame is a set of voxels
    idx, labels, n = idx[np.argsort(first)], labels[np.sort(first)], len(idx)
    if draw(st.booleans()):  # exact coordinates: voxel centres, maybe jittered inside their voxel
        pts = g.centres_of(idx) + rng.uniform(-0.49, 0.49, (n, 3)) * g.voxel_size * draw(st.sampled_from([0.0, 1.0]))
        inside = np.all((pts >= np.array(g.lower)) & (pts < np.array(g.upper)), axis=1)
        pts, labels = pts[inside], labels[inside]
        return SparseOccupancy(
            grid=GridSpecModel.from_grid(g),
            points=Array.from_numpy(pts.astype(np.float64)),
            labels=Array.from_numpy(labels),
        )
    dtype = np.uint8 if max(g.shape) <= 256 and draw(st.booleans()) else np.uint16
    return SparseOccupancy(
        grid=GridSpecModel.from_grid(g), voxels=Array.from_numpy(idx.astype(dtype)), labels=Array.from_numpy(labels)
    )


@st.composite
def matrices(draw, rows, cols):
    m = np.random.default_rng(draw(rng_seeds)).normal(size=(rows, cols)) * draw(
        st.sampled_from([0.0, 1.0, 1e-300, 1e300])
    )
    m.flat[0] = draw(st.just(1.0) | small_finite)
    return m.tolist()


@st.composite
def camera_images(draw) -> CameraImage:
    enc = draw(st.sampled_from(["jpeg", "png", "raw_rgb8"]))
    w, h = draw(st.integers(1, 8)), draw(st.integers(1, 8))
    data = np.random.default_rng(draw(rng_seeds)).bytes(w * h * 3 if enc == "raw_rgb8" else draw(st.integers(0, 64)))
    return CameraImage(
        camera=draw(st.text(max_size=12)),
        encoding=enc,
        width=w,
        height=h,
        data=data,
        intrinsics=draw(matrices(3, 3)),
        extrinsics=draw(matrices(4, 4)),
    )


@st.composite
def camera_frames(draw, stream=streams, max_n: int = 64) -> CameraFrame:
    images = [draw(camera_images())] * 6 if draw(st.integers(0, 3)) == 0 else []  # six copies: cheap to draw
    return CameraFrame(
        stream=draw(stream),
        seq=draw(seqs),
        stamp=draw(finite),
        images=images,
        gt_occupancy=draw(st.none() | occupancies(max_n)),
        sent_at=draw(st.just(0.0) | finite),
    )


@st.composite
def occupancy_frames(draw, stream=streams, max_n: int = 64, grid=None) -> OccupancyFrameMsg:
    return OccupancyFrameMsg(
        stream=draw(stream),
        seq=draw(seqs),
        stamp=draw(finite),
        source=draw(st.text(max_size=20)),
        occupancy=draw(occupancies(max_n, grid)),
        timings_ms=draw(timings),
        sent_at=draw(st.just(0.0) | finite),
    )


@st.composite
def pose_estimates(draw, stream=streams) -> PoseEstimate:
    return PoseEstimate(
        stream=draw(stream),
        seq=draw(seqs),
        stamp=draw(finite),
        pose=draw(matrices(4, 4)),
        status=draw(st.sampled_from(["ok", "lost", "reinitialised"])),
        timings_ms=draw(timings),
        sent_at=draw(finite),
    )


@st.composite
def trajectories(draw, stream=streams) -> Trajectory:
    rng = np.random.default_rng(draw(rng_seeds))
    t = draw(st.integers(0, 20))
    return Trajectory(
        stream=draw(stream),
        seqs=Array.from_numpy(rng.integers(0, 2**62, t)),
        stamps=Array.from_numpy(rng.normal(size=t)),
        poses=Array.from_numpy(rng.normal(size=(t, 4, 4))),
    )


@st.composite
def map_tile_queries(draw, stream=streams) -> MapTileQuery:
    opt = st.none() | i64 | st.integers(-5, 5)
    return MapTileQuery(stream=draw(stream), ix_min=draw(opt), ix_max=draw(opt), iy_min=draw(opt), iy_max=draw(opt))


@st.composite
def map_tiles(draw, stream=streams, ix=None, iy=None, tile_m=None, max_m: int = 50) -> MapTile:
    rng = np.random.default_rng(draw(rng_seeds))
    m = draw(st.integers(0, max_m))
    tm = tile_m if tile_m is not None else draw(st.floats(0.1, 1e3))
    return MapTile(
        stream=draw(stream),
        ix=ix if ix is not None else draw(i64),
        iy=iy if iy is not None else draw(i64),
        tile_m=tm,
        seq=draw(seqs),
        points=Array.from_numpy(rng.uniform(-1e3, 1e3, (m, 3))),
        labels=Array.from_numpy(rng.integers(0, 256, m).astype(np.uint8)),
    )


@st.composite
def map_updates(draw, stream=streams, max_tiles: int = 3, max_m: int = 50) -> MapUpdate:
    tm = draw(st.floats(0.1, 1e3))
    cells = draw(st.lists(st.tuples(st.integers(-3, 3), st.integers(-3, 3)), max_size=max_tiles, unique=True))
    return MapUpdate(
        stream=draw(stream),
        seq=draw(seqs),
        reset=draw(st.booleans()),
        tile_m=tm,
        tiles=[draw(map_tiles(stream, ix, iy, tm, max_m)) for ix, iy in cells],
    )


@st.composite
def map_infos(draw, stream=streams) -> MapInfo:
    b = st.none() | st.tuples(finite, finite, finite)
    return MapInfo(
        stream=draw(stream),
        tile_m=draw(finite),
        tile_count=draw(i64),
        voxel_count=draw(i64),
        last_seq=draw(st.none() | i64),
        bounds_min=draw(b),
        bounds_max=draw(b),
        tiles=draw(st.lists(st.tuples(i64, i64), max_size=5)),
    )


@st.composite
def error_events(draw, stream=streams) -> ErrorEvent:
    return ErrorEvent(
        stream=draw(stream | st.just("*")),
        worker=draw(st.text(max_size=20)),
        code=draw(st.sampled_from(sorted(ERROR_CODES))),
        message=draw(st.text(max_size=80)),
        key=draw(st.text(max_size=40)),
        seq=draw(st.none() | i64),
        stamp=draw(finite),
    )


@st.composite
def worker_healths(draw, stream=streams) -> WorkerHealth:
    stage = st.builds(StageStats, count=i64, p50_ms=finite, p90_ms=finite, p99_ms=finite, mean_ms=finite)
    return WorkerHealth(
        worker=draw(st.text(max_size=20)),
        role=draw(st.sampled_from(["inference", "registration", "map"])),
        pid=draw(i64),
        uptime_s=draw(finite),
        policy=draw(st.sampled_from(["lossless", "latest"])),
        streams=draw(st.lists(stream, max_size=3)),
        counters=draw(st.dictionaries(st.text(max_size=12), i64, max_size=5)),
        queue_depth=draw(st.dictionaries(stream, i64, max_size=3)),
        stages=draw(st.dictionaries(st.text(max_size=12), stage, max_size=3)),
    )


STRATEGIES = {
    "camera_frame": camera_frames,
    "occupancy_frame": occupancy_frames,
    "pose_estimate": pose_estimates,
    "trajectory": trajectories,
    "map_tile_query": map_tile_queries,
    "map_tile": map_tiles,
    "map_update": map_updates,
    "map_info": map_infos,
    "error_event": error_events,
    "worker_health": worker_healths,
}
assert set(STRATEGIES) == set(MESSAGES)


def any_message(stream=streams):
    return st.sampled_from(KINDS).flatmap(lambda k: STRATEGIES[k](stream=stream))


# ------------------------------------------------------------------ mutations (numpy RNG from a drawn seed: cheap, so
# each hypothesis example checks many mutants; hypothesis draws the message and the seed, and shrinks both)

SPECIAL_INTS = [0, -1, 1, 255, 256, 65536, 2**31, 2**32, 2**63 - 1, 2**64 - 1, -(2**63)]
SPECIAL_FLOATS = [float("nan"), float("inf"), -float("inf"), -0.0, 5e-324, 1.7976931348623157e308, -1e308, 1e-300]
SPECIAL_TEXT = ["", "float16", "object", "<f8", "camera_frame", "*", "occvo/**", "\x00", "\U0001f980" * 10, "a" * 300]


def rng_garbage(rng: np.random.Generator, depth: int = 2):
    """A value of any msgpack type, the awkward ones (NaN, inf, -0.0, 64-bit extremes, nesting) made likely."""
    r = int(rng.integers(0, 12 if depth > 0 else 10))
    if r == 0:
        return None
    if r == 1:
        return bool(rng.integers(0, 2))
    if r == 2:
        return SPECIAL_INTS[int(rng.integers(0, len(SPECIAL_INTS)))]
    if r == 3:
        return int(rng.integers(-(2**63), 2**63 - 1, dtype=np.int64))
    if r == 4:
        return SPECIAL_FLOATS[int(rng.integers(0, len(SPECIAL_FLOATS)))]
    if r == 5:
        return float(rng.normal() * 10.0 ** int(rng.integers(-300, 300)))
    if r == 6:
        return SPECIAL_TEXT[int(rng.integers(0, len(SPECIAL_TEXT)))]
    if r == 7:
        return "".join(chr(int(c)) for c in rng.integers(32, 0x2FF, int(rng.integers(0, 12))))
    if r in (8, 9):
        return rng.bytes(int(rng.integers(0, 40)))
    if r == 10:
        return [rng_garbage(rng, depth - 1) for _ in range(int(rng.integers(0, 4)))]
    return {str(rng_garbage(rng, 0)): rng_garbage(rng, depth - 1) for _ in range(int(rng.integers(0, 4)))}


def _paths(obj, prefix=()):
    """Every path to a node of a msgpack structure (dict keys and list indices)."""
    yield prefix
    if isinstance(obj, dict):
        for k, v in obj.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(obj, list):
        for i, v in enumerate(obj):
            yield from _paths(v, prefix + (i,))


def _get(obj, path):
    for p in path:
        obj = obj[p]
    return obj


def _pick(rng, seq):
    return seq[int(rng.integers(0, len(seq)))]


STRUCT_OPS = ["replace", "replace", "delete", "extra", "array", "array", "version", "kind", "deep"]


def mutate_structure(obj, rng: np.random.Generator, op: str | None = None):
    """One change to a decoded message: a field's value, type or presence, an Array's dtype/shape/data, the version,
    the kind, or deep nesting. Returns (mutant, op)."""
    obj = copy.deepcopy(obj)
    op = op or _pick(rng, STRUCT_OPS)
    paths = list(_paths(obj))
    if op == "version":
        obj["schema_version"] = _pick(rng, [2, 3, 2**64 - 1, 0, -1, -(2**63), "1", 1.0, True, None, b"\x01", [1]])
        return obj, op
    if op == "kind":
        obj["kind"] = _pick(rng, KINDS + ["", "camera", "Camera_Frame", None, 7, b"camera_frame", ["camera_frame"]])
        return obj, op
    if op == "array":
        arrays = [
            p for p in paths if isinstance(_get(obj, p), dict) and {"dtype", "shape", "data"} <= set(_get(obj, p))
        ]
        if arrays:
            a = _get(obj, _pick(rng, arrays))
            what = _pick(rng, ["dtype", "shape", "shape", "data"])
            if what == "dtype":
                a["dtype"] = _pick(
                    rng,
                    [
                        "uint8",
                        "uint16",
                        "int32",
                        "int64",
                        "float32",
                        "float64",
                        "float16",
                        "bool",
                        "object",
                        "<f8",
                        "",
                        3,
                    ],
                )
            elif what == "shape":
                a["shape"] = (
                    [
                        _pick(rng, [0, 1, 2, 3, 4, -1, -(2**63), 2**31, 2**32, 2**63 - 1, 2**64 - 1, 16])
                        for _ in range(int(rng.integers(0, 4)))
                    ]
                    if rng.random() < 0.8
                    else rng_garbage(rng, 1)
                )
            else:
                d = a["data"] if isinstance(a["data"], bytes) else b""
                cut = int(rng.integers(0, len(d) + 1))
                a["data"] = _pick(
                    rng,
                    [
                        d[:cut],
                        d + b"\x00" * int(rng.integers(1, 9)),
                        b"",
                        d[:cut] + d[cut:][::-1],
                        np.frombuffer(d[: len(d) // 8 * 8], np.float64).copy().clip(-1e300, 1e300).tobytes()
                        if rng.random() < 0.5
                        else np.full(len(d) // 8, np.nan).tobytes(),
                    ],
                )
            return obj, op
        op = "replace"
    if op == "deep":
        value = rng_garbage(rng, 0)
        for _ in range(int(rng.integers(10, 200))):
            value = [value] if rng.random() < 0.5 else {"k": value}
        path = _pick(rng, paths)
        if not path:
            return value, op
        _get(obj, path[:-1])[path[-1]] = value
        return obj, op
    path = _pick(rng, paths)
    if not path:
        return rng_garbage(rng), "replace_root"
    parent, key = _get(obj, path[:-1]), path[-1]
    if op == "delete":
        del parent[key]
    elif op == "extra" and isinstance(_get(obj, path), dict):
        _get(obj, path)[str(rng_garbage(rng, 0))] = rng_garbage(rng, 1)
    else:
        parent[key] = rng_garbage(rng)
    return obj, op


def mutate_bytes(data: bytes, rng: np.random.Generator) -> bytes:
    """Bit flips, byte overwrites, truncation, insertion, deletion, duplication of the encoded bytes."""
    b = bytearray(data)
    for _ in range(int(rng.integers(1, 5))):
        op = _pick(rng, ["flip", "flip", "set", "truncate", "insert", "delete", "dup"])
        n = len(b)
        if op == "flip" and n:
            b[int(rng.integers(0, n))] ^= 1 << int(rng.integers(0, 8))
        elif op == "set" and n:
            b[int(rng.integers(0, n))] = _pick(
                rng, [0x00, 0xFF, 0xC1, 0xC0, 0xDC, 0xDF, 0xCF, 0xCB, 0x7F, 0x80, int(rng.integers(0, 256))]
            )
        elif op == "truncate":
            del b[int(rng.integers(0, n + 1)) :]
        elif op == "insert":
            i = int(rng.integers(0, n + 1))
            b[i:i] = rng.bytes(int(rng.integers(1, 17)))
        elif op == "delete" and n:
            i = int(rng.integers(0, n))
            del b[i : i + int(rng.integers(1, 17))]
        elif op == "dup" and n:
            i = int(rng.integers(0, n))
            b[i:i] = b[i : i + int(rng.integers(1, 33))]
    return bytes(b)


def pack(obj) -> bytes | None:
    """msgpack bytes of a (mutated) structure; None when msgpack itself cannot carry it (ints beyond 64 bits)."""
    try:
        return msgpack.packb(obj, use_bin_type=True)
    except (OverflowError, TypeError, ValueError):
        return None


def unpack(data: bytes):
    return msgpack.unpackb(data, raw=False)


# ------------------------------------------------------------------ the codec contract


def _arrays_of(model):
    if isinstance(model, Array):
        yield model
    elif isinstance(model, BaseModel):
        for name in type(model).model_fields:
            yield from _arrays_of(getattr(model, name))
    elif isinstance(model, (list, tuple)):
        for x in model:
            yield from _arrays_of(x)
    elif isinstance(model, dict):
        for x in model.values():
            yield from _arrays_of(x)


def assert_valid(model) -> None:
    """A decoded model is a real message: its arrays are readable and it survives a second round trip unchanged."""
    assert type(model) in MESSAGES.values()
    for a in _arrays_of(model):
        assert a.to_numpy().shape == tuple(a.shape)
    again = encode(model, 1 << 30)
    assert decode(again, type(model), 1 << 30) == model
    assert encode(decode(again, type(model), 1 << 30), 1 << 30) == again


def check_decode(data: bytes, expect=None, max_bytes: int = 1 << 30, area: str = "codec"):
    """decode returns a valid model or raises CodecError with a known code and a message; nothing else."""
    COUNT[area] += 1
    try:
        model = decode(data, expect, max_bytes)
    except CodecError as exc:
        assert exc.code in ERROR_CODES, exc.code
        assert isinstance(exc.message, str) and exc.message, exc
        return exc
    assert_valid(model)
    if expect is not None:
        assert isinstance(model, expect if isinstance(expect, tuple) else (expect,))
    return model


def occ3d_centres(rng: np.random.Generator, n: int) -> np.ndarray:
    return OCC3D_GRID.centres_of(rng.integers(0, OCC3D_GRID.shape, size=(n, 3)))
