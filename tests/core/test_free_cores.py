"""Kernel threads follow the cores other processes leave free (occvo_core.free_cores)."""

from __future__ import annotations

import multiprocessing
import time

from occvo_core.free_cores import WINDOW_S, FreeCores


def _spin(seconds: float) -> None:
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def test_busy_neighbours_leave_one_thread():
    cores = FreeCores()
    n = len(cores.cpus)
    ctx = multiprocessing.get_context("spawn")
    busy = [ctx.Process(target=_spin, args=(3.0,), daemon=True) for _ in range(n)]
    for proc in busy:
        proc.start()
    try:
        time.sleep(1.0)  # the neighbours are up
        cores.threads(n)
        time.sleep(WINDOW_S * 2)
        threads = cores.threads(n)
        assert threads == 1, f"{n} busy neighbours on {n} cores left {cores.free:.2f} free cores, {threads} threads"
        assert cores.free < 0.6 * n
    finally:
        for proc in busy:
            proc.terminate()
            proc.join()


def _own_ticks() -> int:
    with open("/proc/self/stat") as f:
        return sum(int(v) for v in f.read().rsplit(")", 1)[1].split()[11:13])  # utime, stime


def _busy_ticks(cpus: set[int]) -> int:
    """Busy jiffies of `cpus`, all processes' (this one's included)."""
    busy = 0
    with open("/proc/stat") as f:
        for line in f:
            name, *fields = line.split()
            if name.startswith("cpu") and name[3:].isdigit() and int(name[3:]) in cpus:
                ticks = [int(v) for v in fields[:8]]
                busy += sum(ticks) - ticks[3] - ticks[4]
    return busy


def test_own_work_is_not_a_neighbour():
    """The neighbours' share is the cores' busy time less this process's own. Checked as that identity over a window
    in which this process did a known amount of work (its own CPU time, not wall time: on a busy machine the spin
    gets what the scheduler gives it), so other processes' load, whatever it is, cannot decide the outcome."""
    cores = FreeCores()
    n = len(cores.cpus)
    before, busy0, own0 = cores._sample(), _busy_ticks(cores.cpus), _own_ticks()
    cpu0 = time.process_time()
    while time.process_time() - cpu0 < 0.3:  # 30 jiffies of own work, however long the machine makes it take
        pass
    after, busy1, own1 = cores._sample(), _busy_ticks(cores.cpus), _own_ticks()
    own, counted = own1 - own0, after[1] - before[1]
    # others' ticks between the paired reads (microseconds apart) are the only slack
    assert own >= 25 and abs(counted - (busy1 - busy0 - own)) <= 3, (
        f"neighbours' busy ticks {counted}, cores' busy ticks {busy1 - busy0} less own {own}"
    )
    assert 1 <= cores.threads(3 * n) <= n
