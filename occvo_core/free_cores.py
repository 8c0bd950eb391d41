"""Kernel threads by the cores other processes leave free.

A parallel kernel ends with its slowest slice: when a neighbour holds one of two cores, the second thread waits for
it and two threads run slower than one. So "all cores" (threads=0) means the cores that were free over the last
fraction of a second, read from the kernel's CPU counters (Linux /proc); elsewhere it means every core."""

from __future__ import annotations

import os
import time

WINDOW_S = 0.25  # the counters tick every 10 ms: a shorter window reads noise
TAKEN_AT = 0.4  # a core counts as taken once others keep it this busy (a map service's bursts stay below)
_IDLE_FIELDS = (3, 4)  # idle, iowait of a /proc/stat cpu line


def _allowed_cpus() -> set[int]:
    try:
        return set(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return set(range(os.cpu_count() or 1))


class FreeCores:
    """Free cores among those this process may run on, refreshed at most every WINDOW_S."""

    def __init__(self):
        self.cpus = _allowed_cpus()
        self.free = float(len(self.cpus))  # until the first window has passed: an idle machine
        self._last = self._sample()

    def _sample(self) -> tuple[float, float, float] | None:
        """(time, busy jiffies of this process's cpus less its own, all jiffies of those cpus); None off Linux."""
        try:
            busy = total = 0
            with open("/proc/stat") as f:
                for line in f:
                    name, *fields = line.split()
                    if not name.startswith("cpu") or name == "cpu":
                        continue
                    if not name[3:].isdigit() or int(name[3:]) not in self.cpus:
                        continue
                    ticks = [int(v) for v in fields[:8]]
                    total += sum(ticks)
                    busy += sum(ticks) - sum(ticks[i] for i in _IDLE_FIELDS)
            with open("/proc/self/stat") as f:
                own = sum(int(v) for v in f.read().rsplit(")", 1)[1].split()[11:13])  # utime, stime
        except (OSError, ValueError, IndexError):
            return None
        return time.monotonic(), busy - own, total

    def threads(self, most: int) -> int:
        """Threads for the next kernels: the free cores, at least 1 and at most `most`."""
        last = self._last  # lanes in threads call this at once: one window's ends, not two
        if last is not None and time.monotonic() - last[0] >= WINDOW_S:
            sample = self._sample()
            if sample is not None and sample[2] > last[2]:
                others = (sample[1] - last[1]) / (sample[2] - last[2]) * len(self.cpus)
                self.free = len(self.cpus) - max(0.0, others)
                self._last = sample
        taken = int(len(self.cpus) - self.free + 1.0 - TAKEN_AT)
        return max(1, min(most, len(self.cpus) - taken))


FREE_CORES = FreeCores()  # one reader a process: lanes in threads share its window
