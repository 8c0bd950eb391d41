"""Structured JSON logs and a worker's counters and stage latency percentiles (its stats queryable's reply)."""

from __future__ import annotations

import json
import logging
import sys
import threading
from collections import defaultdict, deque

import numpy as np

from occvo_schemas.models import StageStats
from occvo_services.store.url import redact

# ---------------------------------------------------------------- logs


class _JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {
            "ts": round(record.created, 6),
            "level": record.levelname.lower(),
            "logger": record.name,
            "event": redact(record.getMessage()),
        }
        # a store URL's password reaches no log line, whichever field or error text carries it
        out.update({k: redact(v) if isinstance(v, str) else v for k, v in getattr(record, "fields", {}).items()})
        return json.dumps(out, default=lambda v: redact(str(v)))


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
