"""What every occvo worker shares: a liveliness token, a stats queryable, error events and graceful shutdown around
the stream lanes (services/flow.py), counters and logs (services/telemetry.py), OS tuning (services/os_tuning.py);
its Zenoh sessions come from services/sessions.py."""

from __future__ import annotations

import logging
import os
import threading
import time
import uuid
from collections import defaultdict
from collections.abc import Callable

import zenoh

from occvo_schemas import keys
from occvo_schemas.codec import CodecError, decode, encode
from occvo_schemas.models import ErrorEvent, WorkerHealth
from occvo_services.flow import LANE_THREADS, SeqTracker, StageQueue, StreamLane
from occvo_services.ingress import TurnedAway, enqueue
from occvo_services.lane_eviction import longest_idle
from occvo_services.limits import MAX_KEY_CHARS, MAX_MESSAGE_CHARS, Admission, ErrorBudget, clip
from occvo_services.memory import CHECK_EVERY_S, MemoryCap
from occvo_services.os_tuning import name_os_thread, trim_heap
from occvo_services.query_gate import QueryGate
from occvo_services.sessions import open_worker_session
from occvo_services.stop_signals import set_on_signal
from occvo_services.store.url import redact
from occvo_services.strand import pool
from occvo_services.telemetry import Stats, log_event, structured_logger
from occvo_services.wire import blocking, encoding
from occvo_services.worker_config import DEFAULT_ENDPOINT, Policy, WorkerConfig

__all__ = [  # importers of these names from here predate the split
    "DEFAULT_ENDPOINT",
    "Policy",
    "SeqTracker",
    "StageQueue",
    "StreamLane",
    "WorkerConfig",
    "log_event",
    "structured_logger",
]


class Worker:
    role: str = "worker"
    input_context: dict | None = None  # the validators' context of its input (codec.decode)

    def __init__(self, config: WorkerConfig):
        self.config = config
        self.worker_id = config.worker_id or f"{self.role}-{uuid.uuid4().hex[:8]}"
        self.log = structured_logger(f"occvo.{self.role}", config.log_level)
        self.stats = Stats()
        self.stopping = threading.Event()
        self.shutdown_requested = threading.Event()  # SIGTERM / SIGINT (run_forever), also while waiting for a router
        self.started = time.time()
        self.lanes: dict[str, StreamLane] = {}
        self.trackers: dict[str, SeqTracker] = defaultdict(lambda: SeqTracker(config.max_seq_jump))
        self._lanes_lock = threading.Lock()
        self.admission = Admission(config.max_streams, config.max_streams_per_client)
        self.error_budget = ErrorBudget(config.error_events_per_s, config.error_burst)
        self.memory = MemoryCap(config.max_rss_mb)
        self.turned_away = TurnedAway()  # lossless: frames a full queue turned away (services/ingress.py)
        self.query_gates: dict[str, QueryGate] = {}  # one a queryable (bounded()), by its handler's name
        self._evicted_at = 0.0
        self._declared: list = []
        self._retired: dict[str, StreamLane] = {}
        # the streams' lanes take turns on these threads (services/strand.py): as many whatever the streams
        self.lane_pool = pool(LANE_THREADS, f"{self.role}-lane", initializer=name_os_thread)
        self._sweeper = threading.Thread(target=self._sweep_idle, name=f"{self.role}-idle", daemon=True)
        self.session: zenoh.Session | None = None

    # -- lifecycle
    def start(self) -> Worker:
        """On the network: its session (a router not up yet waited for, config.router_wait_s), queryables and
        token. A shutdown requested while it waits leaves it unstarted (session None)."""
        self.session = open_worker_session(
            self.config.connect,
            self.config.router_wait_s,
            self.shutdown_requested,
            lambda why: log_event(self.log, "waiting for the router", why=why, wait_s=self.config.router_wait_s),
        )
        if self.session is None:
            return self
        self._declared.append(self.session.declare_queryable(keys.stats(self.worker_id), self._on_stats))
        self.declare()
        self.token = self.session.liveliness().declare_token(keys.alive(self.role, self.worker_id))
        self._sweeper.start()
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
            lane.strand.wait_idle(timeout=60)  # its frame in hand finished; nothing more is taken
            left = lane.queue.qsize()
            if left:
                self.stats.inc("abandoned_at_shutdown", left)
        self.drain()
        self.lane_pool.shutdown(wait=False)  # idle unless a lane's frame did not finish in time
        for entity in (self.token, *self._declared):
            try:
                entity.undeclare()
            except Exception as exc:  # noqa: BLE001 - the session may already be gone; shutting down regardless
                self.log.debug("undeclare at shutdown failed: %s", exc)
        for gate in self.query_gates.values():
            gate.close()  # the queries in work are answered (their session is still open)
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
        requested = self.shutdown_requested
        set_on_signal(requested)
        if self.start().session is None:
            return 0
        while not requested.wait(0.2):  # short waits keep the main thread responsive to signals
            continue
        log_event(self.log, "shutdown requested", worker=self.worker_id)
        self.stop()
        return 0

    def _sweep_idle(self) -> None:
        """Lanes idle_stream_s without a frame leave (their stream's state is given back, their place freed)."""
        idle_s = self.config.idle_stream_s
        while not self.stopping.wait(min(1.0, idle_s / 4)):
            now = time.monotonic()
            for lane in list(self.lanes.values()):
                if lane.idle_for(now) >= idle_s:
                    lane.retire_when_idle()

    # -- helpers for roles
    def lane(self, stream: str, handler: Callable[[str, object], None]) -> StreamLane:
        with self._lanes_lock:
            lane = self.lanes.get(stream)
            if lane is None:
                lane = self.lanes[stream] = StreamLane(self, stream, handler, self._retired.pop(stream, None))
                log_event(self.log, "new stream", stream=stream)
            lane.handed()
            return lane

    def retire_lane(self, lane: StreamLane, why: str = "idle") -> bool:
        """An idle lane's end (idle_stream_s without a frame, or evicted for memory): unless a frame is on its way to
        it, it leaves, the stream's state is given back (retire_stream) and its place in the admission frees up. True
        if the lane's thread is to end."""
        with self._lanes_lock:
            if lane.pending or lane.queue.qsize() or self.lanes.get(lane.stream) is not lane:
                return False
            del self.lanes[lane.stream]
            self._retired[lane.stream] = lane  # a new lane of the stream waits for this one's thread
            self.admission.leaves(lane.stream)  # its place is free while its state is given back (a snapshot)
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
                else:  # a frame came meanwhile: the stream keeps its place
                    self.admission.stays(lane.stream)
        if why == "reclaimed":
            self.stats.inc("streams_reclaimed")
            log_event(self.log, "idle stream's place reclaimed for a new stream", stream=lane.stream)
        elif why == "memory":
            self.stats.inc("streams_evicted_memory")
            log_event(
                self.log,
                "idle stream evicted: memory near max_rss_mb",
                stream=lane.stream,
                rss_mb=round(self.memory.rss()),
                max_rss_mb=self.config.max_rss_mb,
            )
        else:
            self.stats.inc("streams_retired")
            log_event(self.log, "idle stream retired", stream=lane.stream, idle_s=self.config.idle_stream_s)
        trim_heap()  # the lane thread's malloc arena keeps its free pages otherwise (the inference worker's RSS grew with every stream served)
        return True

    def retire_stream(self, stream: str) -> None:
        """Give back an idle stream's per-stream state (roles override); its lane is gone already."""

    def enqueue(
        self, sample: zenoh.Sample, expect, handler: Callable[[str, object], None], judge_seq: bool = True, place=None
    ) -> None:
        """A stream message in, queued on its lane or answered at once (services/ingress.py)."""
        enqueue(self, sample, expect, handler, judge_seq, place)

    def relieve_memory(self) -> None:
        """Over the eviction mark of max_rss_mb: the lane idle longest ends (one at a time, checked every
        CHECK_EVERY_S at most; services/lane_eviction.py)."""
        now = time.monotonic()
        if now - self._evicted_at < CHECK_EVERY_S or not self.memory.over_evict_mark():
            return
        with self._lanes_lock:
            lane = longest_idle(self.lanes.values(), now)
            if lane is not None and lane.evict("memory"):
                self._evicted_at = now

    def release_unserved(self, stream: str) -> None:
        """An admitted stream's frame went nowhere: without a lane its place goes back."""
        with self._lanes_lock:
            if stream not in self.lanes:
                self.admission.release(stream)

    def lane_entered(self, lane: StreamLane) -> None:
        """A frame handed to lane() is queued or answered (lane.pending counts those on their way)."""
        with self._lanes_lock:
            lane.entered()

    def reports_input(self, stream: str) -> bool:
        """Whether this worker reports a stream's message that did not decode (roles where every worker receives
        every stream's messages override: one of them reports)."""
        return True

    def store_away(self) -> str | None:
        """Why the role's store cannot be reached now, or None (roles with a store override)."""
        return None

    def not_held(self, stream: str, seq: int) -> None:
        """A frame answered store_unavailable before its lane (roles with a store override: the stream's later
        frames wait for it)."""

    def frame_cost_mb(self, msg) -> float:
        """What handling `msg` will cost this worker's memory (MB), charged against max_rss_mb before it is queued
        (roles override; services/memory.py)."""
        return 0.0

    def decode_input(self, sample: zenoh.Sample, expect, client: str | None = None):
        """Decode and check a sample; on any problem report it (against `client`'s error budget) and return None."""
        key = str(sample.key_expr)
        stream = keys.stream_of(key)
        self.stats.inc("frames_in")
        try:
            msg = decode(sample.payload.to_bytes(), expect, self.config.max_message_bytes, self.input_context)
        except CodecError as exc:
            if self.reports_input(stream):
                self.report_error(stream, exc.code, exc.message, key, client=client)
            return None
        if getattr(msg, "stream", stream) != stream:
            self.report_error(
                stream,
                "stream_mismatch",
                f"message says stream {msg.stream!r} but came on {key}",
                key,
                getattr(msg, "seq", None),
                client=client,
            )
            return None
        return msg

    def check_seq(self, stream: str, seq: int, key: str) -> bool:
        ok, code, message = self.trackers[stream].check(seq)
        if code:
            self.stats.inc(code)
            self.report_error(stream, code, message, key, seq)
        return ok

    def report_error(
        self, stream: str, code: str, message: str, key: str = "", seq: int | None = None, client: str | None = None
    ) -> ErrorEvent:
        """Log and publish an error event, keys and messages clipped, at most error_events_per_s a client (the
        client given, else the stream's owner, else the stream: one client's flood of keys shares one budget; the
        rest counted as errors_suppressed and named in the next event). Flow control (stream_full) is an answer, one a
        frame its client sent well formed, not an error: never suppressed (a client not told would not send the frame
        again, and the frames waiting for it would wait in vain), and logged at debug level only."""
        self.stats.inc("errors")
        stream = stream if keys.STREAM_RE.match(stream) else "*"
        client = client or self.admission.owner(stream) or stream
        flow = code == "stream_full"
        suppressed = 0 if flow else self.error_budget.take(client)
        message = clip(redact(message), MAX_MESSAGE_CHARS)  # a store error's text names the store: no password
        if suppressed:
            message += f" (+{suppressed} error events of this client suppressed before this one)"
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
        fields = event.model_dump(exclude={"kind", "schema_version"})
        level = logging.DEBUG if flow else logging.WARNING
        log_event(self.log, "error", level, client=clip(client, MAX_KEY_CHARS), **fields)
        if self.session is not None and not self.session.is_closed():
            try:
                self.session.put(
                    keys.errors(event.stream if event.stream != "*" else "_"),
                    encode(event),
                    **blocking("error_event"),
                )  # a report is never dropped
            except Exception as exc:  # noqa: BLE001
                log_event(self.log, "cannot publish error event", logging.ERROR, error=repr(exc))
        return event

    def bounded(self, handler: Callable[[zenoh.Query], None]) -> Callable[[zenoh.Query], None]:
        """A queryable callback answering on its own pool, at most max_queries_per_client of a client's queries (and
        max_wildcard_queries wildcard ones) at once. One gate a queryable: one `occvo/**` get is a query to each of
        a worker's queryables at once, and must not be refused by itself."""
        name = handler.__name__.strip("_")
        gate = self.query_gates[name] = QueryGate(
            self.config.max_queries_per_client,
            self.config.max_wildcard_queries,
            self._refuse_query,
            name,
            identity=self.config.client_identity,
        )

        def answer(query: zenoh.Query) -> None:
            try:
                handler(query)
            except Exception as exc:  # noqa: BLE001 - a worker never dies of one query
                stream = keys.stream_of(str(query.key_expr))
                self.reply_error(query, stream, "internal", f"{type(exc).__name__}: {exc}")

        return gate.wrap(answer)

    def _refuse_query(self, query: zenoh.Query, client: str, message: str) -> None:
        self.stats.inc("queries_refused")
        self.reply_error(query, keys.stream_of(str(query.key_expr)), "busy", message)

    def reply_error(self, query: zenoh.Query, stream: str, code: str, message: str) -> None:
        event = self.report_error(stream, code, message, str(query.key_expr))
        query.reply_err(encode(event), encoding=encoding("error_event"))

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
        query.reply(keys.stats(self.worker_id), encode(self.health()), encoding=encoding("worker_health"))
