"""What every occvo worker shares: Zenoh sessions, bounded per-stream stage queues, sequence checks, counters,
latency percentiles, a liveliness token, a stats queryable, error events, structured logs and graceful shutdown."""

from __future__ import annotations

import ctypes
import json
import logging
import os
import queue
import signal
import socket
import sys
import threading
import time
import uuid
from collections import defaultdict, deque
from collections.abc import Callable
from pathlib import Path
from typing import Literal

import numpy as np
import zenoh
from pydantic import BaseModel, ConfigDict, Field, model_validator

from occvo_core.errors import ConfigError
from schemas import keys
from schemas.codec import DEFAULT_MAX_BYTES, CodecError, decode, encode
from schemas.models import ErrorEvent, StageStats, WorkerHealth
from services.limits import MAX_KEY_CHARS, MAX_MESSAGE_CHARS, Admission, ErrorBudget, clip

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"
Policy = Literal["lossless", "latest"]


# ---------------------------------------------------------------- sessions


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


ZENOH_CONFIG_ENV = "OCCVO_ZENOH_CONFIG"  # a zenoh json5 for client sessions: TLS certificates, credentials (deploy/)
CLIENT_RETRY = "{period_init_ms: 100, period_max_ms: 500, period_increase_factor: 2}"
# Zenoh reassembles a fragmented message up to this many bytes and drops it beyond (its default, 1 GiB, let a 512 MiB
# put cost the router and a worker 500 MB before the codec's check). The codec's limit, so every message that reaches
# a worker's decode is within it; the registration worker splits bigger map updates (deploy/*.json5 set it too)
TRANSPORT_MAX_BYTES = DEFAULT_MAX_BYTES
_ZENOH_DEFAULT_MAX = 1 << 30


def limit_messages(c: zenoh.Config, max_bytes: int = TRANSPORT_MAX_BYTES) -> zenoh.Config:
    """Set the transport's largest reassembled message, unless the config file set its own."""
    if json.loads(c.get_json("transport/link/rx/max_message_size")) == _ZENOH_DEFAULT_MAX:
        c.insert_json5("transport/link/rx/max_message_size", str(max_bytes))
    return c


def zenoh_config(
    mode: str = "client", connect: str | None = None, listen: str | None = None, base: str | Path | None = None
) -> zenoh.Config:
    """Loopback-friendly config: no multicast scouting, explicit endpoints only. Client sessions start from
    `base` (default: the file named by $OCCVO_ZENOH_CONFIG) and retry a lost router every 0.5 s at most, so
    workers and clients reconnect within half a second of a router restart (zenoh's default waits up to 4 s)."""
    base = base or (os.environ.get(ZENOH_CONFIG_ENV) if mode == "client" else None)
    try:
        c = zenoh.Config.from_file(str(base)) if base else zenoh.Config()
    except Exception as exc:  # noqa: BLE001 - zenoh names the key, we name the file
        raise ConfigError(f"zenoh config {base}: {exc}") from None
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    if connect:
        c.insert_json5("connect/endpoints", json.dumps([connect]))
    if listen:
        c.insert_json5("listen/endpoints", json.dumps([listen]))
    if mode == "client" and json.loads(c.get_json("connect/retry")) is None:
        c.insert_json5("connect/retry", CLIENT_RETRY)
    return limit_messages(c)


def open_session(connect: str = DEFAULT_ENDPOINT, base: str | Path | None = None) -> zenoh.Session:
    return zenoh.open(zenoh_config("client", connect=connect, base=base))


def open_router(listen: str | None = None, config_path: str | Path | None = None) -> zenoh.Session:
    """An in-process Zenoh router, from a json5 config file (deploy/router.json5) or a listen endpoint."""
    if config_path is not None:
        c = zenoh.Config.from_file(str(config_path))
        if listen:
            c.insert_json5("listen/endpoints", json.dumps([listen]))
        return zenoh.open(limit_messages(c))
    return zenoh.open(zenoh_config("router", listen=listen or DEFAULT_ENDPOINT))


def router_endpoint(config_path: str | Path) -> str:
    """The first listen endpoint of a router json5 config, for workers and clients to connect to."""
    import json5

    try:
        eps = json5.loads(Path(config_path).read_text())["listen"]["endpoints"]
        return eps[0]
    except Exception as exc:  # noqa: BLE001
        raise ConfigError(f"{config_path}: no listen/endpoints[0] ({exc})") from None


# ---------------------------------------------------------------- logs


class _JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {
            "ts": round(record.created, 6),
            "level": record.levelname.lower(),
            "logger": record.name,
            "event": record.getMessage(),
        }
        out.update(getattr(record, "fields", {}))
        return json.dumps(out, default=str)


def structured_logger(name: str, level: str = "INFO") -> logging.Logger:
    log = logging.getLogger(name)
    if not log.handlers:
        h = logging.StreamHandler(sys.stderr)
        h.setFormatter(_JsonFormatter())
        log.addHandler(h)
        log.propagate = False
    log.setLevel(level.upper())
    return log


def log_event(log: logging.Logger, event: str, level: int = logging.INFO, **fields) -> None:
    log.log(level, event, extra={"fields": fields})


# ---------------------------------------------------------------- counters and latencies


class LatencyWindow:
    """The last `size` samples of one stage, in milliseconds."""

    def __init__(self, size: int = 4096):
        self.samples: deque[float] = deque(maxlen=size)
        self.count = 0

    def add(self, ms: float) -> None:
        self.samples.append(ms)
        self.count += 1

    def summary(self) -> StageStats:
        a = np.array(self.samples) if self.samples else np.zeros(1)
        p50, p90, p99 = np.percentile(a, [50, 90, 99])
        return StageStats(count=self.count, p50_ms=p50, p90_ms=p90, p99_ms=p99, mean_ms=float(a.mean()))


class Stats:
    def __init__(self):
        self._lock = threading.Lock()
        self.counters: dict[str, int] = defaultdict(int)
        self.stages: dict[str, LatencyWindow] = defaultdict(LatencyWindow)
        for name in ("frames_in", "frames_out", "drops", "errors"):
            self.counters[name] = 0

    def inc(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] += n

    def observe(self, stage: str, ms: float) -> None:
        with self._lock:
            self.stages[stage].add(ms)

    def snapshot(self) -> tuple[dict[str, int], dict[str, StageStats]]:
        with self._lock:
            return dict(self.counters), {k: v.summary() for k, v in self.stages.items()}


# ---------------------------------------------------------------- flow


class StageQueue:
    """Bounded queue between two stages. lossless: put blocks (backpressure); latest: the oldest item is dropped."""

    def __init__(self, maxsize: int, policy: Policy, on_drop: Callable[[object], None], stop: threading.Event):
        self.q: queue.Queue = queue.Queue(maxsize=maxsize)
        self.policy = policy
        self.on_drop = on_drop
        self.stop = stop

    def put(self, item) -> bool:
        """False when the item could not be queued because the worker is stopping."""
        if self.policy == "lossless":
            while not self.stop.is_set():
                try:
                    self.q.put(item, timeout=0.1)
                    return True
                except queue.Full:
                    continue
            return False
        while True:
            try:
                self.q.put_nowait(item)
                return True
            except queue.Full:
                try:
                    self.on_drop(self.q.get_nowait())
                except queue.Empty:
                    continue  # a consumer took the oldest meanwhile: there is room now, put again

    def get(self, timeout: float):
        return self.q.get(timeout=timeout)

    def qsize(self) -> int:
        return self.q.qsize()


class SeqTracker:
    """Per-stream sequence check. seq 0 starts a new trajectory; a gap is reported as missing, a step back as out of order."""

    def __init__(self, max_jump: int | None = None):
        self.expected: int | None = None
        self.max_jump = max_jump

    def check(self, seq: int) -> tuple[bool, str | None, str | None]:
        """(accept, error code, message). A step forward of more than max_jump is reported and not adopted: one
        stray seq must not make every following real frame a step back."""
        if self.expected is None or seq == 0 or seq == self.expected:
            self.expected = seq + 1
            return True, None, None
        if self.max_jump is not None and seq - self.expected >= self.max_jump:
            return (
                False,
                "seq_jump",
                (
                    f"seq {seq} is {seq - self.expected + 1} after seq {self.expected - 1}, beyond "
                    f"the window of {self.max_jump}; dropped"
                ),
            )
        if seq > self.expected:
            msg = f"missing seq {self.expected}..{seq - 1} ({seq - self.expected} frames) before seq {seq}"
            self.expected = seq + 1
            return True, "missing_seq", msg
        return False, "out_of_order", f"seq {seq} arrived after seq {self.expected - 1}; dropped"


# ---------------------------------------------------------------- worker base


class WorkerConfig(BaseModel):
    """One config for every worker; fields a role does not use are ignored by it (deploy/*.json5)."""

    model_config = ConfigDict(extra="forbid")
    connect: str = DEFAULT_ENDPOINT
    worker_id: str | None = None
    policy: Policy = "lossless"
    queue_size: int = Field(4, ge=1, le=1024)
    max_message_bytes: int = Field(DEFAULT_MAX_BYTES, ge=1024)
    log_level: str = "INFO"
    # what one client may cost (services/limits.py); the defaults fit a 2-core machine
    max_streams: int = Field(64, ge=1)  # streams a worker serves at once; more get a stream_limit error event
    max_streams_per_client: int = Field(16, ge=1)  # of them, per client (the stream id's prefix before its first '.')
    idle_stream_s: float = Field(30.0, gt=0)  # a stream without frames this long gives back its lane (and its memory)
    max_seq_jump: int = Field(100_000, ge=1)  # a seq this far beyond the next expected is reported, not adopted
    error_events_per_s: float = Field(20.0, gt=0)  # error events a stream may cause a second (bursts of error_burst)
    error_burst: int = Field(100, ge=1)
    max_query_tiles: int = Field(64, ge=1)  # map: tiles in one reply to a region or wildcard query (a page)
    max_query_streams: int = Field(16, ge=1)  # registration: trajectories in one reply to a wildcard query
    # inference worker
    source: Literal["replay", "model"] = "replay"
    device: Literal["auto", "cpu", "cuda"] = "auto"
    model_weights: str | None = None  # TinyOccNet state_dict (services.occupancy_model)
    checkpoint: str | None = None  # TPV-Former checkpoint of the model source (occvo train-occ)
    torch_threads: int = Field(1, ge=1)
    # model source: voxels the network is less sure of than this are reported free (OccupancyPredictor)
    min_confidence: float = Field(0.0, ge=0, lt=1)
    min_ground_confidence: float = Field(0.0, ge=0, lt=1)
    # registration worker
    # shards: registration workers sharing the streams; this one registers the streams of `shard`
    # (schemas.keys.shard_of: CRC-32 of the stream id mod shards). `occvo up` sets both from a role's count
    shard: int = Field(0, ge=0)
    shards: int = Field(1, ge=1, le=1024)
    tile_m: float = Field(20.0, gt=0)
    occvo_config: str | None = None
    # registration: cores each stream's kernels may use, 0 = all. Streams already run side by side in threads, and
    # the inference worker wants a core; poses are the same for any value
    kernel_threads: int = Field(1, ge=0)
    # registration: niceness added to the threads doing the work after a pose (loop closure, map update, eviction,
    # restores) and writing snapshots, so that the cores go to other streams' poses first. 0: the lanes' priority
    after_pose_nice: int = Field(10, ge=0, le=19)
    # registration: a frame's work after its pose taking longer than this is logged with its steps (its stream's next
    # frame waits for it)
    slow_after_pose_s: float = Field(0.5, gt=0)
    # registration: call every kernel once at start-up, before taking frames (compiled on a fresh install, else
    # loaded from numba's cache; see occvo_core/warm_up.py)
    warm_up: bool = True
    # durable state (SQLite file; the registration worker and the map service may share one)
    store_path: str | None = None
    snapshot_every: int = Field(
        20, ge=1
    )  # registration: frames between state snapshots at least (a journal covers the rest)
    # registration: snapshots of a stream take at most this share of its time; a big map is snapshotted less often
    # (a resume replays more journal) instead of stalling every stream (a 10^6-voxel state is ~200 MB, ~1 s to write);
    # None: every snapshot_every frames whatever they cost
    snapshot_max_share: float | None = Field(0.02, gt=0, le=1)
    working_radius_m: float | None = Field(None, gt=0)  # registration: map farther from the ego goes to the store
    store_sync: Literal["full", "normal"] = (
        "full"  # registration: SQLite synchronous; normal survives kill -9, not power loss
    )

    @model_validator(mode="after")
    def _shard_in_range(self) -> WorkerConfig:
        if self.shard >= self.shards:
            raise ValueError(f"shard {self.shard} is not one of shards 0..{self.shards - 1}")
        return self

    @classmethod
    def load(cls, path: str | Path | None, **overrides) -> WorkerConfig:
        import json5

        data = {}
        if path is not None:
            try:
                data = json5.loads(Path(path).read_text())
            except Exception as exc:  # noqa: BLE001
                raise ConfigError(f"{path}: {exc}") from None
        data.update({k: v for k, v in overrides.items() if v is not None})
        try:
            return cls.model_validate(data)
        except Exception as exc:  # noqa: BLE001
            raise ConfigError(f"worker config {path or ''}: {exc}") from None


class StreamLane:
    """One stream's bounded queue and the thread that runs the stage on it, in arrival (= sequence) order."""

    def __init__(
        self, worker: Worker, stream: str, handler: Callable[[str, object], None], after: StreamLane | None = None
    ):
        self.worker, self.stream, self.handler = worker, stream, handler
        self.busy = False
        self.pending = 0  # frames handed to this lane and not yet in its queue (Worker.enqueue); guarded by _lanes_lock
        self.after = after  # the stream's retired lane, still giving back its state: this one starts when it is done
        self.queue = StageQueue(worker.config.queue_size, worker.config.policy, self._dropped, worker.stopping)
        self.thread = threading.Thread(target=self._run, name=f"{worker.role}-{stream}", daemon=True)
        self.thread.start()

    def _dropped(self, item) -> None:
        self.worker.stats.inc("drops")
        log_event(self.worker.log, "dropped oldest frame", logging.DEBUG, stream=self.stream)

    def _run(self) -> None:
        name_os_thread(f"lane-{self.stream}")
        if self.after is not None:
            self.after.thread.join()
            self.after = None
        while not self.worker.stopping.is_set():
            try:  # blocks: a stop puts None, an idle stream's lane ends (no polling: 500 idle lanes cost 16% of a core)
                item = self.queue.get(timeout=self.worker.config.idle_stream_s)
            except queue.Empty:
                if self.worker.retire_lane(self):
                    return
                continue
            if item is None:
                continue
            self.busy = True
            try:
                self.handler(self.stream, item)  # the frame in hand is always finished, even when stopping
            except Exception as exc:  # noqa: BLE001 - a worker never dies of one frame
                seq = getattr(item[0], "seq", None) if isinstance(item, tuple) and item else None
                if isinstance(exc, CodecError):  # e.g. an output over the size limit: the frame's problem, named so
                    self.worker.report_error(
                        self.stream, exc.code, f"seq {seq}: output not sent: {exc.message}", seq=seq
                    )
                else:
                    self.worker.report_error(self.stream, "internal", f"{type(exc).__name__}: {exc}", seq=seq)
                log_event(self.worker.log, "stage failed", logging.ERROR, stream=self.stream, error=repr(exc))
            finally:
                self.busy = False


class Worker:
    role: str = "worker"

    def __init__(self, config: WorkerConfig):
        self.config = config
        self.worker_id = config.worker_id or f"{self.role}-{uuid.uuid4().hex[:8]}"
        self.log = structured_logger(f"occvo.{self.role}", config.log_level)
        self.stats = Stats()
        self.stopping = threading.Event()
        self.started = time.time()
        self.lanes: dict[str, StreamLane] = {}
        self.trackers: dict[str, SeqTracker] = defaultdict(lambda: SeqTracker(config.max_seq_jump))
        self._lanes_lock = threading.Lock()
        self.admission = Admission(config.max_streams, config.max_streams_per_client)
        self.error_budget = ErrorBudget(config.error_events_per_s, config.error_burst)
        self._declared: list = []
        self._retired: dict[str, StreamLane] = {}
        self.session: zenoh.Session | None = None

    # -- lifecycle
    def start(self) -> Worker:
        self.session = open_session(self.config.connect)
        self._declared.append(self.session.declare_queryable(keys.stats(self.worker_id), self._on_stats))
        self.declare()
        self.token = self.session.liveliness().declare_token(keys.alive(self.role, self.worker_id))
        log_event(
            self.log,
            "started",
            worker=self.worker_id,
            connect=self.config.connect,
            policy=self.config.policy,
            pid=os.getpid(),
        )
        return self

    def declare(self) -> None:
        """Declare the role's subscribers and queryables (append them to self._declared)."""

    def stop(self) -> None:
        """Stop taking input, finish the frame in hand on every lane, then leave the network."""
        if self.stopping.is_set():
            return
        self.stopping.set()
        for lane in list(self.lanes.values()):
            try:
                lane.queue.q.put_nowait(None)  # wakes a lane waiting for a frame; a full queue's lane is busy anyway
            except queue.Full:
                pass
        for lane in list(self.lanes.values()):
            lane.thread.join(timeout=60)
            left = lane.queue.qsize()
            if left:
                self.stats.inc("abandoned_at_shutdown", left)
        self.drain()
        for entity in (self.token, *self._declared):
            try:
                entity.undeclare()
            except Exception as exc:  # noqa: BLE001 - the session may already be gone; shutting down regardless
                self.log.debug("undeclare at shutdown failed: %s", exc)
        if self.session is not None:
            self.session.close()
        self.after_leaving()
        counters, _ = self.stats.snapshot()
        log_event(self.log, "stopped", worker=self.worker_id, **counters)  # always the last line of a worker's log

    def drain(self) -> None:
        """Wait for work a lane handed to other threads (before leaving the network: it may publish)."""

    def after_leaving(self) -> None:
        """Shutdown work once off the network (e.g. the registration worker's last snapshots)."""

    def run_forever(self) -> int:
        """Until SIGTERM or SIGINT; returns the exit code."""
        requested = threading.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: requested.set())
        self.start()
        while not requested.wait(0.2):  # short waits keep the main thread responsive to signals
            continue
        log_event(self.log, "shutdown requested", worker=self.worker_id)
        self.stop()
        return 0

    # -- helpers for roles
    def lane(self, stream: str, handler: Callable[[str, object], None]) -> StreamLane:
        with self._lanes_lock:
            lane = self.lanes.get(stream)
            if lane is None:
                lane = self.lanes[stream] = StreamLane(self, stream, handler, self._retired.pop(stream, None))
                log_event(self.log, "new stream", stream=stream)
            lane.pending += 1
            return lane

    def retire_lane(self, lane: StreamLane) -> bool:
        """An idle lane's end: unless a frame is on its way to it, it leaves, the stream's state is given back
        (retire_stream) and its place in the admission frees up. True if the lane's thread is to end."""
        with self._lanes_lock:
            if lane.pending or lane.queue.qsize() or self.lanes.get(lane.stream) is not lane:
                return False
            del self.lanes[lane.stream]
            self._retired[lane.stream] = lane  # a new lane of the stream waits for this one's thread
        try:
            self.retire_stream(lane.stream)
        except Exception as exc:  # noqa: BLE001 - the state stays in memory then; the worker goes on
            log_event(self.log, "retiring an idle stream failed", logging.ERROR, stream=lane.stream, error=repr(exc))
        finally:
            with self._lanes_lock:
                if self._retired.get(lane.stream) is lane:
                    del self._retired[lane.stream]
                if lane.stream not in self.lanes:
                    self.admission.release(lane.stream)
        self.stats.inc("streams_retired")
        log_event(self.log, "idle stream retired", stream=lane.stream, idle_s=self.config.idle_stream_s)
        trim_heap()  # the lane thread's malloc arena keeps its free pages otherwise (inference +28% after 300 streams)
        return True

    def retire_stream(self, stream: str) -> None:
        """Give back an idle stream's per-stream state (roles override); its lane is gone already."""

    def enqueue(self, sample: zenoh.Sample, expect, handler: Callable[[str, object], None]) -> None:
        """Decode a stream message, check its sequence number and queue it on its stream's lane with its hop
        latency; bad messages are reported by decode_input and check_seq, never raised."""
        t_recv = time.time()
        msg = self.decode_input(sample, expect)
        if msg is None or self.stopping.is_set():
            return
        refused = self.admission.admit(msg.stream)
        if refused is not None:
            self.stats.inc("streams_refused")
            self.report_error(msg.stream, "stream_limit", refused, str(sample.key_expr), msg.seq)
            return
        if not self.check_seq(msg.stream, msg.seq, str(sample.key_expr)):
            with self._lanes_lock:
                if msg.stream not in self.lanes:  # admitted for nothing: its place goes back
                    self.admission.release(msg.stream)
            return
        # a sent_at a day off (e.g. 1e308) would give an infinite hop: no hop latency then, not a failed stage
        hop_ms = (t_recv - msg.sent_at) * 1000.0 if 0 < msg.sent_at and abs(t_recv - msg.sent_at) < 86400 else 0.0
        lane = self.lane(msg.stream, handler)
        try:
            lane.queue.put((msg, hop_ms, time.perf_counter()))
        finally:
            with self._lanes_lock:
                lane.pending -= 1

    def decode_input(self, sample: zenoh.Sample, expect):
        """Decode and check a sample; on any problem report it and return None."""
        key = str(sample.key_expr)
        stream = keys.stream_of(key)
        self.stats.inc("frames_in")
        try:
            msg = decode(sample.payload.to_bytes(), expect, self.config.max_message_bytes)
        except CodecError as exc:
            self.report_error(stream, exc.code, exc.message, key)
            return None
        if getattr(msg, "stream", stream) != stream:
            self.report_error(
                stream,
                "stream_mismatch",
                f"message says stream {msg.stream!r} but came on {key}",
                key,
                getattr(msg, "seq", None),
            )
            return None
        return msg

    def check_seq(self, stream: str, seq: int, key: str) -> bool:
        ok, code, message = self.trackers[stream].check(seq)
        if code:
            self.stats.inc(code)
            self.report_error(stream, code, message, key, seq)
        return ok

    def report_error(self, stream: str, code: str, message: str, key: str = "", seq: int | None = None) -> ErrorEvent:
        """Log and publish an error event, keys and messages clipped, at most error_events_per_s a stream (the
        rest counted as errors_suppressed and named in the next event)."""
        self.stats.inc("errors")
        stream = stream if keys.STREAM_RE.match(stream) else "*"
        suppressed = self.error_budget.take(stream)
        message = clip(message, MAX_MESSAGE_CHARS)
        if suppressed:
            message += f" (+{suppressed} error events of this stream suppressed before this one)"
        event = ErrorEvent(
            stream=stream,
            worker=self.worker_id,
            code=code,
            message=message,
            key=clip(key, MAX_KEY_CHARS),
            seq=seq,
            stamp=time.time(),
        )
        if suppressed is None:
            self.stats.inc("errors_suppressed")
            return event
        log_event(self.log, "error", logging.WARNING, **event.model_dump(exclude={"kind", "schema_version"}))
        if self.session is not None and not self.session.is_closed():
            try:
                self.session.put(
                    keys.errors(event.stream if event.stream != "*" else "_"),
                    encode(event),
                    congestion_control=zenoh.CongestionControl.BLOCK,
                )  # a report is never dropped
            except Exception as exc:  # noqa: BLE001
                log_event(self.log, "cannot publish error event", logging.ERROR, error=repr(exc))
        return event

    def reply_error(self, query: zenoh.Query, stream: str, code: str, message: str) -> None:
        event = self.report_error(stream, code, message, str(query.key_expr))
        query.reply_err(encode(event))

    def health(self) -> WorkerHealth:
        counters, stages = self.stats.snapshot()
        return WorkerHealth(
            worker=self.worker_id,
            role=self.role,
            pid=os.getpid(),
            uptime_s=time.time() - self.started,
            policy=self.config.policy,
            streams=self.streams(),
            counters=counters,
            queue_depth={s: l.queue.qsize() for s, l in self.lanes.items()},
            stages=stages,
        )

    def streams(self) -> list[str]:
        return sorted(set(self.lanes) | set(self.trackers))

    def _on_stats(self, query: zenoh.Query) -> None:
        query.reply(keys.stats(self.worker_id), encode(self.health()))


def lower_priority(nice: int) -> bool:
    """Run the calling thread `nice` steps below the thread that made it (Linux threads are tasks with their own
    niceness; raising it needs no privilege). False where that is not possible: the thread keeps its priority."""
    if nice <= 0:
        return True
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, min(19, os.getpriority(os.PRIO_PROCESS, tid) + nice))
    except (OSError, AttributeError):
        return False
    return True


def name_os_thread(name: str | None = None) -> None:
    """Name the calling OS thread (first 15 bytes; default: its Python name), so `top -H`, `ps -L` and
    /proc/<pid>/task/*/comm tell the lanes and background threads apart (Python < 3.14 leaves them all "python")."""
    try:
        ctypes.CDLL(None).prctl(15, (name or threading.current_thread().name).encode()[:15], 0, 0, 0)  # PR_SET_NAME
    except (OSError, AttributeError):
        return  # no prctl (not Linux): the thread works the same, unnamed


def set_thread_nice(tid: int, nice: int) -> bool:
    """Set a thread's niceness; False where not allowed (raising priority needs CAP_SYS_NICE or RLIMIT_NICE)."""
    try:
        os.setpriority(os.PRIO_PROCESS, tid, nice)
    except (OSError, AttributeError):
        return False
    return True


_held_lock = threading.Lock()
_held: dict[int, tuple[int, int]] = {}  # tid -> (holds, its niceness once none is left)


def hold_priority(tid: int, nice: int) -> bool:
    """Keep thread `tid` at niceness `nice` or better until release_priority(tid). Holds nest: a niced after-pose
    thread its waiting lane raised (priority inheritance) that also holds the store's write lock (a priority ceiling)
    goes back to its niceness when both are over. True if the thread runs at `nice` or better now; False where
    raising it is not allowed (CAP_SYS_NICE or RLIMIT_NICE)."""
    with _held_lock:
        if tid in _held:
            count, rest = _held[tid]
            _held[tid] = (count + 1, rest)
            return True
        try:
            rest = os.getpriority(os.PRIO_PROCESS, tid)
        except (OSError, AttributeError):
            return False
        if rest <= nice:
            return True  # nothing to raise (and nothing for release_priority to undo)
        if not set_thread_nice(tid, nice):
            return False
        _held[tid] = (1, rest)
        return True


def release_priority(tid: int) -> None:
    """End one hold_priority(tid) that returned True; the last one puts the thread back to its niceness."""
    with _held_lock:
        if tid not in _held:
            return
        count, rest = _held[tid]
        if count > 1:
            _held[tid] = (count - 1, rest)
        else:
            del _held[tid]
            set_thread_nice(tid, rest)


def large_blocks_from_mmap(threshold: int = 16 << 20, trim: int = 64 << 20) -> bool:
    """Fix glibc's mmap threshold and heap trim threshold (False where malloc is not glibc's). By default the mmap
    threshold rises to the largest block freed, up to 32 MB: then even the map's big arrays come from the heap, which
    fragments, and a worker's RSS creeps up over hours (3,600-frame drive: median RSS +11% from the first half to the
    second). Fixed, blocks over `threshold` (map arrays, snapshot copies) are mmapped and returned when freed; a
    frame's temporaries (up to a few MB) come from a heap that keeps up to `trim` free at its top. Session 7 fixed
    128 KB: every temporary was then a fresh mapping, faulted in page by page: 20x the page faults, registration
    p50 23.8 ms instead of 13.3 on a loaded stream (scratch profile of load stream 2, frames 200 to 300)."""
    try:
        libc = ctypes.CDLL("libc.so.6")
        return bool(libc.mallopt(-3, threshold)) and bool(libc.mallopt(-1, trim))  # M_MMAP_THRESHOLD, M_TRIM_THRESHOLD
    except (OSError, AttributeError):
        return False


def trim_heap() -> bool:
    """Give the heap's free pages back to the system now (glibc's malloc_trim; False elsewhere). Once, after start-up
    work whose temporaries are gone (the kernels' warm-up left 43 MB free but resident); not per frame: trimmed pages
    fault in again (README, Reliability: eight-stream p99 42 to 64 ms with a trim every 5 s)."""
    try:
        return bool(ctypes.CDLL("libc.so.6").malloc_trim(0))
    except (OSError, AttributeError):
        return False


def worker_main(worker_cls: type[Worker], argv: list[str] | None = None, extra_args: Callable | None = None) -> int:
    """`python -m services.<role>_worker [--config deploy/x.json5] [--connect ...] ...`"""
    import argparse

    p = argparse.ArgumentParser(prog=f"python -m {worker_cls.__module__}", description=worker_cls.__doc__)
    p.add_argument("--config", help="worker json5 config (deploy/*.json5)")
    p.add_argument("--connect", help=f"router endpoint (default {DEFAULT_ENDPOINT})")
    p.add_argument("--worker-id")
    p.add_argument("--policy", choices=["lossless", "latest"])
    p.add_argument("--queue-size", type=int)
    p.add_argument("--max-message-bytes", type=int)
    p.add_argument("--log-level")
    if extra_args:
        extra_args(p)
    args = vars(p.parse_args(argv))
    config = WorkerConfig.load(args.pop("config"), **args)
    large_blocks_from_mmap()
    return worker_cls(config).run_forever()
