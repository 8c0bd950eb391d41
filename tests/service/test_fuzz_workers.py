"""Fuzzing the three workers through real Zenoh (router + workers as threads of this process, loopback, free port).

Every payload published to a worker's input key must give its normal output (an occupancy frame from the inference
worker, a pose from the registration worker, an applied map update visible in map/info for the map service) or an
ErrorEvent; every query a reply (a bad tile-query payload: one reply_err naming the decoding error). Each case has its
own streams ("lanes") with one message in flight per lane, so each answer belongs to one message: exactly one terminal
answer per message (an output or an error), a gap's missing_seq before it. Decoding each payload here predicts the
error code; a mirror of the map predicts map/info and tile replies. The workers' stats counters must equal what was
sent and observed, and each worker still takes a valid frame, a gap and a step back afterwards."""

from __future__ import annotations

import threading
import time
from collections import Counter, defaultdict

import numpy as np
import pytest
import zenoh
from fuzz_messages import (
    COUNT,
    KINDS,
    STRATEGIES,
    camera_frames,
    map_tile_queries,
    map_updates,
    mutate_bytes,
    mutate_structure,
    occupancy_frames,
    pack,
    rng_seeds,
    unpack,
)
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from occvo_core.grid import OCC3D_GRID
from occvo_schemas import keys
from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.models import (
    Array,
    CameraFrame,
    ErrorEvent,
    GridSpecModel,
    MapInfo,
    MapTile,
    MapTileQuery,
    MapUpdate,
    OccupancyFrameMsg,
    PoseEstimate,
    SparseOccupancy,
    Trajectory,
    WorkerHealth,
)
from occvo_services.local import InProcessService
from occvo_services.sessions import open_session

MAXB = 256 * 1024  # the workers' max_message_bytes: small, so oversize payloads are cheap to make
FUZZ = dict(
    deadline=None,
    database=None,
    derandomize=True,
    suppress_health_check=list(HealthCheck),
    phases=[Phase.explicit, Phase.generate],
)  # no shrinking against a live service: failures print the payload
ANSWER_S = 20.0
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")
START = COUNT["workers"]


# ------------------------------------------------------------------ what the workers publish, by stream


class Observer:
    """Error events, occupancy frames, poses and map updates as they come, per stream and per worker role."""

    def __init__(self, session: zenoh.Session):
        self.cv = threading.Condition()
        self.by_stream: dict[str, list[tuple]] = defaultdict(list)  # (what, role, code, seq)
        self.totals: Counter = Counter()  # (role, what) and (role, code)
        self.bad_outputs: list[str] = []
        self.internal: list[str] = []  # messages of 'internal' errors: a stage raised, a bug to fix
        self.subs = [
            session.declare_subscriber(keys.errors("*"), self._on_error),
            session.declare_subscriber(keys.occupancy("*"), self._on_occupancy),
            session.declare_subscriber(keys.pose("*"), self._on_pose),
            session.declare_subscriber(keys.map_updates("*"), self._on_update),
        ]

    def _add(self, stream, what, role, code=None, seq=None):
        with self.cv:
            self.by_stream[stream].append((what, role, code, seq))
            self.totals[(role, what)] += 1
            if code:
                self.totals[(role, code)] += 1
            self.cv.notify_all()

    def _decode(self, sample, model):
        try:
            return decode(sample.payload.to_bytes(), model, 1 << 30)
        except CodecError as exc:  # a worker published something invalid: a bug, reported by the tests
            self.bad_outputs.append(f"{sample.key_expr}: {exc}")
            return None

    def _on_error(self, sample):
        ev = self._decode(sample, ErrorEvent)
        if ev is not None:
            if ev.code == "internal":
                self.internal.append(f"{ev.worker}: {ev.message}")
            self._add(keys.stream_of(str(sample.key_expr)), "error", ev.worker.split("-")[0], ev.code, ev.seq)

    def _on_occupancy(self, sample):
        stream = keys.stream_of(str(sample.key_expr))
        if stream.startswith("fi"):  # the inference worker's output; fr* streams carry this test's own input
            msg = self._decode(sample, OccupancyFrameMsg)
            if msg is not None:
                self._add(stream, "output", "inference", seq=msg.seq)

    def _on_pose(self, sample):
        msg = self._decode(sample, PoseEstimate)
        if msg is not None:
            self._add(keys.stream_of(str(sample.key_expr)), "output", "registration", seq=msg.seq)

    def _on_update(self, sample):
        stream = keys.stream_of(str(sample.key_expr))
        if not stream.startswith("fm"):  # fm* streams carry this test's own map updates
            if self._decode(sample, MapUpdate) is not None:
                with self.cv:
                    self.totals[("registration", "update")] += 1

    def answers(self, stream: str, role: str) -> list[tuple]:
        with self.cv:
            return [a for a in self.by_stream[stream] if a[1] == role]

    def close(self):
        for s in self.subs:
            s.undeclare()


class Fuzz:
    """The service, the observer, what was sent, and a mirror of the map service's maps."""

    def __init__(self, svc: InProcessService):
        self.svc = svc
        self.session = open_session(svc.endpoint)
        self.obs = Observer(self.session)
        self.ids = {w.role: w.worker_id for w in svc.workers}
        self.sent: Counter = Counter()  # camera / occupancy / map_update / map_applied / query
        self.next_seq: dict[str, int] = defaultdict(int)  # per lane, after the last frame a worker took
        self.maps: dict[str, dict] = {}  # stream -> {"tile_m", "tiles": {(ix, iy): (n, lo, hi)}, "last_seq"}

    def put(self, key: str, payload: bytes, what: str) -> None:
        self.sent[what] += 1
        COUNT["workers"] += 1
        self.session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)

    def stats(self) -> dict[str, dict[str, int]]:
        out = {}
        for role, wid in self.ids.items():
            replies = [r for r in self.session.get(keys.stats(wid), timeout=10.0) if r.ok is not None]
            assert len(replies) == 1, role
            out[role] = decode(replies[0].ok.payload.to_bytes(), WorkerHealth).counters
        return out

    def expected_counters(self) -> dict[str, dict[str, int]]:
        """Counters the stats queryables must show, from what was sent and what came back."""
        t, s = self.obs.totals, self.sent
        return {
            "inference": {
                "frames_in": s["camera"],
                "errors": t[("inference", "error")],
                "frames_out": t[("inference", "output")],
                "missing_seq": t[("inference", "missing_seq")],
                "out_of_order": t[("inference", "out_of_order")],
            },
            "registration": {
                "frames_in": s["occupancy"] + t[("inference", "output")],
                "errors": t[("registration", "error")],
                "frames_out": t[("registration", "output")],
                "missing_seq": t[("registration", "missing_seq")],
                "out_of_order": t[("registration", "out_of_order")],
            },
            "map": {
                "frames_in": s["map_update"] + t[("registration", "update")],
                "errors": t[("map", "error")],
                "frames_out": s["map_applied"] + t[("registration", "update")],
            },
        }

    def settle(self, timeout: float = 30.0) -> dict:
        """Wait until every worker's counters equal what was sent and observed; return both for the assert."""
        deadline = time.monotonic() + timeout
        while True:
            got, want = self.stats(), self.expected_counters()
            seen = {r: {k: got[r].get(k, 0) for k in want[r]} for r in want}
            seen["registration"]["frames_out"] += got["registration"].get(
                "republished", 0
            )  # resends answered from the store
            if seen == want or time.monotonic() > deadline:
                return seen, want
            time.sleep(0.2)


@pytest.fixture(scope="module")
def fuzz():
    from occvo_core import OccVO
    from occvo_core.frame import OccupancyFrame

    rng = np.random.default_rng(0)  # compile (or load) the odometry's numba kernels before the timed part
    vo = OccVO()
    for i in range(2):
        vo.step(
            OccupancyFrame(
                OCC3D_GRID.centres_of(rng.integers(0, OCC3D_GRID.shape, (200, 3))),
                rng.integers(0, 17, 200).astype(np.uint8),
                index=i,
            )
        )
    # every message answered: the error budget (one client here, test_hostile_clients.py tests it) never bites
    with InProcessService(
        max_message_bytes=MAXB, log_level="CRITICAL", error_burst=1_000_000, error_events_per_s=1e6
    ) as svc:
        f = Fuzz(svc)
        # our subscribers must reach the router before anything is sent: probe every input key until all answer
        deadline = time.monotonic() + 30
        probes = {
            "camera": keys.camera("fprobe"),
            "occupancy": keys.occupancy("fprobe"),
            "map_update": keys.map_updates("fmprobe"),
        }
        while time.monotonic() < deadline and {
            a[1]
            for a in f.obs.answers("fprobe", "inference")
            + f.obs.answers("fprobe", "registration")
            + f.obs.answers("fmprobe", "map")
        } != {"inference", "registration", "map"}:
            for what, key in probes.items():
                f.put(key, b"\xc1", what)
            time.sleep(0.3)
        seen, want = f.settle()
        assert seen == want, (seen, want)
        yield f
        f.obs.close()
        f.session.close()


# ------------------------------------------------------------------ building fuzzed payloads

OCC_GRID = (
    st.just(GridSpecModel())
    | st.just(GridSpecModel())
    | st.just(GridSpecModel(lower=(-80.0, -80.0, -2.0), upper=(80.0, 80.0, 10.0), voxel_size=0.4))
)
BASES = {
    "camera": lambda: camera_frames(stream=st.just("x"), max_n=48),
    "occupancy": lambda: occupancy_frames(stream=st.just("x"), max_n=48, grid=OCC_GRID),
    "map_update": lambda: map_updates(stream=st.just("x"), max_tiles=3, max_m=30),
}
MUTATIONS = (
    ["valid"] * 5
    + ["bytes"] * 4
    + ["struct"] * 4
    + ["wrong_kind", "random", "oversize", "mismatch", "empty"]
    + ["semantic"] * 2
)


@st.composite
def batches(draw, what: str):
    """A few valid base messages of the key's kind, one message of another kind, and a seed for the mutants."""
    bases = [draw(BASES[what]()) for _ in range(3)]
    other = draw(STRATEGIES[draw(st.sampled_from(KINDS))](stream=st.just("x")))
    return bases, other, draw(rng_seeds)


def _semantic(msg, rng):
    """Valid messages with awkward content: empty, one voxel, the 'free' label, a far clock, extreme stamps."""
    r = int(rng.integers(0, 6))
    if r == 0:
        return msg.model_copy(update={"sent_at": float(rng.choice([1e308, -1e308, 1e-300, 1e12]))})
    if r == 1:
        return msg.model_copy(update={"stamp": float(rng.choice([1e308, -1e308, -0.0]))})
    if isinstance(msg, MapUpdate):
        tiles = [
            t.model_copy(
                update={
                    "points": t.points.model_copy(update={"shape": [0, 3], "data": b""}),
                    "labels": t.labels.model_copy(update={"shape": [0], "data": b""}),
                }
            )
            for t in msg.tiles
        ]
        return msg.model_copy(update={"tiles": tiles if r < 4 else [], "reset": r == 5})
    n = [0, 1, 1, 5][r - 2]
    pts = OCC3D_GRID.centres_of(rng.integers(0, OCC3D_GRID.shape, (n, 3)))
    occ = SparseOccupancy.from_points(pts, np.full(n, 17 if r == 3 else 4), OCC3D_GRID, exact=bool(rng.integers(0, 2)))
    if isinstance(msg, CameraFrame):
        return msg.model_copy(update={"gt_occupancy": occ if r != 5 else None})
    return msg.model_copy(update={"occupancy": occ})


def build(what: str, batch, i: int, lane: str, nxt: int) -> tuple[bytes, str]:
    """The i-th payload of a batch for `lane`, given the seq after the last frame a worker took there."""
    bases, other, seed = batch
    rng = np.random.default_rng(seed + i)
    msg = bases[int(rng.integers(0, len(bases)))]
    mode = rng.choice(["next"] * 7 + ["zero", "gap", "back"])
    seq = {"next": nxt, "zero": 0, "gap": nxt + int(rng.integers(1, 4)), "back": max(0, nxt - int(rng.integers(1, 3)))}[
        mode
    ]
    msg = msg.model_copy(update={"stream": lane, "seq": seq})
    op = MUTATIONS[int(rng.integers(0, len(MUTATIONS)))]
    if op == "semantic":
        msg, op = _semantic(msg, rng), "valid"
    raw = encode(msg, 1 << 30)
    if op == "valid":
        return raw, f"valid {mode}"
    if op == "bytes":
        return mutate_bytes(raw, rng), op
    if op == "struct":
        for _ in range(5):
            packed = pack(mutate_structure(unpack(raw), rng)[0])
            if packed is not None:
                return packed, op
        return b"\x00", op
    if op == "wrong_kind":
        return encode(
            other.model_copy(update={"stream": lane})
            if hasattr(other, "stream") and other.kind != "error_event"
            else other,
            1 << 30,
        ), op
    if op == "random":
        return rng.bytes(int(rng.integers(0, 300))), op
    if op == "oversize":
        return (rng.bytes(MAXB + int(rng.integers(1, 100))) if rng.random() < 0.5 else raw + b"\x00" * MAXB), op
    if op == "mismatch":
        return encode(msg.model_copy(update={"stream": lane + "x"}), 1 << 30), op
    return b"", "empty"


# ------------------------------------------------------------------ driving lanes, one message in flight per lane

EXPECT = {"camera": CameraFrame, "occupancy": OccupancyFrameMsg, "map_update": MapUpdate}
ROLE = {"camera": "inference", "occupancy": "registration", "map_update": "map"}
KEY = {"camera": keys.camera, "occupancy": keys.occupancy, "map_update": keys.map_updates}


def predict(what: str, lane: str, payload: bytes):
    """(code of the error event decoding gives, or None with the message that passes to the worker's stream checks)."""
    try:
        msg = decode(payload, EXPECT[what], MAXB)
    except CodecError as exc:
        return exc.code, None
    if msg.stream != lane:
        return "stream_mismatch", None
    return None, msg


def apply_map(f: Fuzz, msg: MapUpdate) -> None:
    m = f.maps.get(msg.stream)
    if m is None or msg.reset:
        m = f.maps[msg.stream] = {"tiles": {}}
    m["tile_m"], m["last_seq"] = msg.tile_m, msg.seq
    for t in msg.tiles:
        p = t.points.to_numpy()
        if len(p) == 0:
            m["tiles"].pop((t.ix, t.iy), None)
        else:
            m["tiles"][(t.ix, t.iy)] = (len(p), p.min(0), p.max(0))


def mirror_info(f: Fuzz, stream: str) -> MapInfo:
    m = f.maps[stream]
    tiles = m["tiles"]
    lo = hi = None
    if tiles:
        lo = tuple(np.min([v[1] for v in tiles.values()], axis=0).tolist())
        hi = tuple(np.max([v[2] for v in tiles.values()], axis=0).tolist())
    return MapInfo(
        stream=stream,
        tile_m=m["tile_m"],
        tile_count=len(tiles),
        voxel_count=sum(v[0] for v in tiles.values()),
        last_seq=m["last_seq"],
        bounds_min=lo,
        bounds_max=hi,
        tiles=sorted(tiles),
    )


def query(f: Fuzz, selector: str, payload: bytes | None = None, timeout: float = 10.0):
    f.sent["query"] += 1
    COUNT["workers"] += 1
    return list(f.session.get(selector, payload=payload, timeout=timeout))


def check_map_applied(f: Fuzz, stream: str) -> None:
    want = mirror_info(f, stream)
    deadline = time.monotonic() + 5.0
    while True:
        replies = query(f, keys.map_info(stream))
        got = [decode(r.ok.payload.to_bytes(), MapInfo) for r in replies if r.ok is not None]
        if got == [want] or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    assert got == [want], (got, want)


QUERY_CODES = ("tile_not_found", "bad_query")  # only queries give these: map/info polls below, not published input


def fed(f: Fuzz, lane: str, role: str) -> list[tuple]:
    """The answers a lane's published messages got."""
    return [a for a in f.obs.answers(lane, role) if a[2] not in QUERY_CODES]


def terminal(answer) -> bool:
    """Every message gets exactly one terminal answer; a gap's missing_seq comes before it (same publisher, in order)."""
    return answer[0] == "output" or answer[2] != "missing_seq"


def drive(f: Fuzz, what: str, lanes: list[str], payloads: list, log: Counter) -> None:
    """Send each (lane, builder) when its lane is free; check each message's answer against its decoding here."""
    role = ROLE[what]
    todo = {lane: [b for l, b in payloads if l == lane] for lane in lanes}
    total = {lane: sum(map(terminal, fed(f, lane, role))) for lane in lanes}  # terminal answers each lane ends with
    inflight: dict[str, tuple] = {}
    while any(todo.values()) or inflight:
        for lane in lanes:
            if lane in inflight or not todo[lane]:
                continue
            builder = todo[lane].pop(0)
            payload, op = builder(f.next_seq[lane])
            pre, msg = predict(what, lane, payload)
            base = len(fed(f, lane, role))
            f.put(KEY[what](lane), payload, what)
            if what == "map_update":
                log[(op, pre or "applied")] += 1
                if msg is not None:
                    f.sent["map_applied"] += 1
                    apply_map(f, msg)
                    check_map_applied(f, lane)  # an applied update shows in map/info
                    continue
            total[lane] += 1
            inflight[lane] = (time.monotonic(), base, pre, msg, payload, op)
        with f.obs.cv:
            f.obs.cv.wait(0.02)
        for lane, (t0, base, pre, msg, payload, op) in list(inflight.items()):
            got = fed(f, lane, role)[base:]
            # a held jump's answers come when the frame after it confirms it (before that frame's own): another seq's
            # output or error in this message's window is that frame's (a missing_seq of the previous message aside)
            late = [a for a in got if msg is not None and a[3] is not None and a[3] != msg.seq and terminal(a)]
            got = [a for a in got if not (msg is not None and a[3] is not None and a[3] != msg.seq and terminal(a))]
            if not any(map(terminal, got)):
                assert time.monotonic() - t0 < ANSWER_S, (
                    f"{what} on {lane} ({op}, expected {pre}) unanswered, got {got}: {payload[:300]!r}"
                )
                continue
            del inflight[lane]
            total[lane] += len(late)
            got = got[: [terminal(a) for a in got].index(True) + 1]
            # a missing_seq is published from the subscriber thread, the output from the stage's: the previous
            # message's may come after its output, so here it is only this message's
            got = [a for a in got if terminal(a) or (msg is not None and a[3] == msg.seq)]
            last = got[-1]
            log[(op, last[2] or last[0])] += 1
            assert last[2] != "internal", (f.obs.internal[-1:], what, op, got, payload[:300])
            if pre is not None:  # refused on decoding: that error and nothing else
                assert got == [("error", role, pre, None if pre != "stream_mismatch" else msg_seq(payload))], (
                    what,
                    op,
                    pre,
                    got,
                    payload[:300],
                )
                continue
            assert all(a[3] == msg.seq for a in got), (what, op, msg.seq, got)
            assert all(a[2] == "missing_seq" for a in got[:-1]), got
            if last[0] == "output" or last[2] == "invalid_frame":
                f.next_seq[lane] = msg.seq + 1
            if what == "camera" and msg.gt_occupancy is None:  # the replay source needs the recorded occupancy
                assert last[2] in ("invalid_frame", "out_of_order", "seq_jump", "seq_held"), got
            else:  # its normal output, a frame the odometry refuses, a step back or a jump beyond the window
                assert last[0] == "output" or last[2] in ("invalid_frame", "out_of_order", "seq_jump", "seq_held"), got
                assert what != "camera" or last[2] != "invalid_frame", got
    time.sleep(0.3)
    assert {lane: sum(map(terminal, fed(f, lane, role))) for lane in lanes} == total  # nothing answered twice


def msg_seq(payload: bytes):
    """seq of a message that decodes (for stream_mismatch events, which carry it)."""
    try:
        return unpack(payload).get("seq")
    except Exception:  # noqa: BLE001
        return None


def run_case(f: Fuzz, what: str, lanes: list[str], batch, n: int, log: Counter) -> None:
    # each lane starts with a valid seq 0 (and a map reset), so an example does not depend on the ones before it
    start = [
        (lane, (lambda nxt, lane=lane: (encode(_good(what).model_copy(update={"stream": lane})), "start")))
        for lane in lanes
    ]
    payloads = [
        (lanes[i % len(lanes)], (lambda nxt, i=i, lane=lanes[i % len(lanes)]: build(what, batch, i, lane, nxt)))
        for i in range(n)
    ]
    drive(f, what, lanes, start + payloads, log)


def check_counts_and_survival(f: Fuzz, what: str, lanes: list[str], good) -> None:
    """Stats counters agree with what was sent and seen; then the worker takes valid frames, a gap, a step back."""
    role = ROLE[what]
    seen, want = f.settle()
    assert seen == want, (seen, want)
    assert not f.obs.bad_outputs, f.obs.bad_outputs[:3]
    ok_lane = lanes[0] + "ok"
    if what == "map_update":
        msg = good.model_copy(update={"stream": ok_lane})
        f.put(KEY[what](ok_lane), encode(msg), what)
        f.sent["map_applied"] += 1
        apply_map(f, msg)
        check_map_applied(f, ok_lane)
    else:
        # a jump is passed on by the inference worker and held by the registration worker until its next seq comes
        jump = ["missing_seq", "output"] if what == "camera" else ["seq_held"]
        confirm = ["output"] if what == "camera" else ["missing_seq", "output", "output"]
        for seq, expect in ((0, ["output"]), (3, jump), (4, confirm), (2, ["out_of_order"])):
            base = len(f.obs.answers(ok_lane, role))
            f.put(KEY[what](ok_lane), encode(good.model_copy(update={"stream": ok_lane, "seq": seq})), what)
            deadline = time.monotonic() + ANSWER_S
            while len(f.obs.answers(ok_lane, role)[base:]) < len(expect) and time.monotonic() < deadline:
                time.sleep(0.02)
            time.sleep(0.1)
            assert sorted(a[2] or a[0] for a in f.obs.answers(ok_lane, role)[base:]) == expect, seq
    if what == "camera":  # a frame just under the limit whose occupancy frame would be just over it
        big = _near_limit_frame(lanes[0] + "big")
        base = len(f.obs.answers(big.stream, role))
        f.put(keys.camera(big.stream), encode(big, MAXB), what)
        deadline = time.monotonic() + ANSWER_S
        while not f.obs.answers(big.stream, role)[base:] and time.monotonic() < deadline:
            time.sleep(0.02)
        assert [a[2] for a in f.obs.answers(big.stream, role)[base:]] == ["oversize"], f.obs.internal[-1:]
    seen, want = f.settle()
    assert seen == want, (seen, want)


def _near_limit_frame(stream: str) -> CameraFrame:
    rng = np.random.default_rng(3)
    n = MAXB // 25  # float64 coordinates and a label: 25 bytes a voxel
    while True:
        cells = np.stack(np.unravel_index(rng.permutation(np.prod(OCC3D_GRID.shape))[:n], OCC3D_GRID.shape), axis=1)
        occ = _as_points(OCC3D_GRID.centres_of(cells), rng.integers(0, 17, n))  # a set of voxels: each once
        msg = CameraFrame(stream=stream, seq=0, stamp=0.0, gt_occupancy=occ)
        size = len(encode(msg, 1 << 30))
        if size <= MAXB:
            assert size > MAXB - 40, size  # the occupancy frame adds ~80 bytes (source, timings)
            return msg
        n -= 1


def _as_points(points, labels) -> SparseOccupancy:
    """Occupancy as float64 coordinates (the form whose bytes the fuzz cases bend), not indices with axes."""
    return SparseOccupancy(
        points=Array.from_numpy(np.asarray(points, np.float64)), labels=Array.from_numpy(np.asarray(labels, np.uint8))
    )


def _good(what: str):
    rng = np.random.default_rng(7)
    cells = np.stack(np.unravel_index(rng.permutation(np.prod(OCC3D_GRID.shape))[:100], OCC3D_GRID.shape), axis=1)
    occ = _as_points(OCC3D_GRID.centres_of(cells), rng.integers(0, 17, 100))
    if what == "camera":
        return CameraFrame(stream="x", seq=0, stamp=0.0, gt_occupancy=occ)
    if what == "occupancy":
        return OccupancyFrameMsg(stream="x", seq=0, stamp=0.0, source="replay", occupancy=occ)
    return MapUpdate(
        stream="x",
        seq=0,
        tile_m=20.0,
        reset=True,
        tiles=[MapTile(stream="x", ix=0, iy=0, tile_m=20.0, seq=0, points=occ.points, labels=occ.labels)],
    )


# ------------------------------------------------------------------ the tests


def _fuzz_key(what: str, prefix: str, examples: int, per_example: int):
    lanes = [f"{prefix}{i}" for i in range(6)]
    log: Counter = Counter()

    failures: list[str] = []

    @settings(max_examples=examples, **FUZZ)
    @given(batch=batches(what))
    def run(f, batch):
        try:
            run_case(f, what, lanes, batch, per_example, log)
        except AssertionError as exc:  # hypothesis replays a failing example: keep the first failure's own words
            failures.append(str(exc)[:3000])
            raise

    def checked(f):
        try:
            run(f)
        except AssertionError:
            if failures:
                raise AssertionError(f"first failure: {failures[0]}") from None
            raise

    return lanes, log, checked


@pytest.mark.parametrize(
    "what,prefix,examples", [("camera", "fi", 14), ("occupancy", "fr", 14), ("map_update", "fm", 10)]
)
def test_fuzzed_input_is_answered_and_counted(fuzz, what, prefix, examples, capsys):
    t0 = time.monotonic()
    before = COUNT["workers"]
    lanes, log, run = _fuzz_key(what, prefix, examples, 40)
    run(fuzz)
    check_counts_and_survival(fuzz, what, lanes, _good(what))
    outcomes = Counter()
    for (_op, pre), v in log.items():
        outcomes[pre] += v
    with capsys.disabled():
        print(
            f"\nfuzz {ROLE[what]} worker: {COUNT['workers'] - before} messages in {time.monotonic() - t0:.1f} s; "
            f"outcomes {dict(sorted(outcomes.items()))}"
        )
    assert log[("valid next", "applied")] > 0 or what != "map_update"
    assert sum(v for (op, pre), v in log.items() if pre not in ("applied", "-")) > examples * 5  # many errors exercised


def _query_case(f: Fuzz, rng: np.random.Generator, bases: list[MapTileQuery], other) -> tuple[str, bytes | None, str]:
    """A fuzzed query: a selector on one of the queryables and a payload (none, valid, mutated, garbage)."""
    kind = str(rng.choice(["tile"] * 5 + ["info", "pose", "trajectory", "stats"]))
    if kind == "stats":
        wid = list(f.ids.values())[int(rng.integers(0, 3))]
        return keys.stats(wid), rng.bytes(int(rng.integers(0, 50))) or None, kind
    if kind in ("pose", "trajectory"):
        stream = [f"fr{i}" for i in range(6)][int(rng.integers(0, 6))] if rng.random() < 0.8 else "frnone"
        sel = keys.pose_latest(stream) if kind == "pose" else keys.trajectory(stream)
        return sel, (rng.bytes(int(rng.integers(1, 50))) if rng.random() < 0.3 else None), kind
    stream = [f"fm{i}" for i in range(6)][int(rng.integers(0, 6))] if rng.random() < 0.85 else "fmnone"
    if kind == "info":
        return keys.map_info(stream), (rng.bytes(int(rng.integers(1, 50))) if rng.random() < 0.3 else None), kind
    known = sorted(f.maps.get(stream, {}).get("tiles", {}))

    def index(j):
        r = rng.random()
        if known and r < 0.4:
            return known[int(rng.integers(0, len(known)))][j]
        return "*" if r < 0.6 else ("abc" if r < 0.65 else int(rng.integers(-4, 5)))

    sel = keys.map_tile(stream, index(0), index(1))
    q = bases[int(rng.integers(0, len(bases)))].model_copy(update={"stream": stream})
    raw = encode(q)
    payload = [
        lambda: None,
        lambda: raw,
        lambda: raw,
        lambda: mutate_bytes(raw, rng),
        lambda: pack(mutate_structure(unpack(raw), rng)[0]),
        lambda: rng.bytes(int(rng.integers(1, 80))),
        lambda: encode(other),
        lambda: rng.bytes(MAXB + 1),
    ][int(rng.integers(0, 8))]()
    return sel, payload, "tile"


def _expected_tiles(f: Fuzz, sel: str, bounds: MapTileQuery | None) -> dict[str, int]:
    """Tile keys (and their voxel counts) the map service must return for a tile selector, from the mirror."""
    parts = sel.split("/")
    stream, ixs, iys = parts[1], parts[4], parts[5]
    out = {}
    for (ix, iy), (n, _, _) in f.maps.get(stream, {}).get("tiles", {}).items():
        if (
            (ixs == "*" or ixs == str(ix))
            and (iys == "*" or iys == str(iy))
            and (
                bounds is None
                or (
                    (bounds.ix_min is None or ix >= bounds.ix_min)
                    and (bounds.ix_max is None or ix <= bounds.ix_max)
                    and (bounds.iy_min is None or iy >= bounds.iy_min)
                    and (bounds.iy_max is None or iy <= bounds.iy_max)
                )
            )
        ):
            out[keys.map_tile(stream, ix, iy)] = n
    return out


@settings(max_examples=15, **FUZZ)
@given(
    bases=st.lists(map_tile_queries(stream=st.just("x")), min_size=2, max_size=3),
    other=st.sampled_from(KINDS).flatmap(lambda k: STRATEGIES[k](stream=st.just("fm0"))),
    seed=rng_seeds,
)
def _fuzz_queries(f: Fuzz, bases, other, seed, log: Counter):
    rng = np.random.default_rng(seed)
    for _ in range(40):
        sel, payload, kind = _query_case(f, rng, bases, other)
        replies = query(f, sel, payload)
        assert replies, f"no reply to {sel} with {payload!r:.200}"
        oks = [(str(r.ok.key_expr), r.ok.payload.to_bytes()) for r in replies if r.ok is not None]
        errs = [
            decode(r.err.payload.to_bytes(), ErrorEvent) for r in replies if r.err is not None
        ]  # every error reply is an ErrorEvent
        log[(kind, "ok" if oks else errs[0].code)] += 1
        assert all(e.code != "internal" for e in errs), errs
        if kind == "tile":
            try:
                bounds = decode(payload, MapTileQuery, MAXB) if payload else None
            except CodecError as exc:  # a bad payload: one error reply naming the problem
                assert not oks and [e.code for e in errs] == [exc.code] and "tile query payload" in errs[0].message, (
                    sel,
                    errs,
                )
                continue
            want = _expected_tiles(f, sel, bounds)
            if not want:
                assert not oks and [e.code for e in errs] == ["tile_not_found"], (sel, oks, errs)
                continue
            assert not errs and {k: decode(v, MapTile).points.shape[0] for k, v in oks} == want, (sel, errs)
        elif kind == "info":  # payload ignored: this queryable takes none
            stream = sel.split("/")[1]
            if stream in f.maps:
                assert not errs and [decode(v, MapInfo) for _, v in oks] == [mirror_info(f, stream)], (sel, errs)
            else:
                assert not oks and [e.code for e in errs] == ["tile_not_found"]
        elif kind == "stats":
            assert not errs and len(oks) == 1 and decode(oks[0][1], WorkerHealth).worker == sel.split("/")[2]
        else:
            model = PoseEstimate if kind == "pose" else Trajectory
            assert len(replies) == 1 and (
                (oks and decode(oks[0][1], model).stream == sel.split("/")[1]) or (errs and errs[0].code == "bad_query")
            ), (sel, oks, errs)


def test_fuzzed_queries_are_answered(fuzz, capsys):
    """Tile, info, pose, trajectory and stats queries with fuzzed selectors and payloads: each gets its replies or an
    error reply (a bad tile-query payload: exactly one, with the decoding error), and the counters still agree."""
    t0, before, log = time.monotonic(), COUNT["workers"], Counter()
    _fuzz_queries(fuzz, log=log)
    seen, want = fuzz.settle()
    assert seen == want, (seen, want)
    with capsys.disabled():
        print(
            f"\nfuzz queries: {COUNT['workers'] - before} queries in {time.monotonic() - t0:.1f} s; outcomes {dict(sorted(log.items()))}"
        )
    assert any(k[0] == "tile" and k[1] not in ("ok", "tile_not_found") for k in log)  # bad payloads were exercised


def test_zz_count_of_generated_messages(capsys, record_property):
    """Runs last: the messages generated by both fuzz modules (the codec's in process, these through the workers)."""
    total = COUNT["codec"] + COUNT["workers"]
    record_property("generated_messages", total)
    with capsys.disabled():
        print(
            f"\nfuzz total: {total} generated messages (codec {COUNT['codec']}, through workers {COUNT['workers'] - START})"
        )
    assert COUNT["workers"] - START >= 2000 or COUNT["workers"] - START < 100  # the whole module ran, or only this test
    if COUNT["codec"]:  # tests/service/test_fuzz_codec.py ran in this session too
        assert total >= 10_000, total
