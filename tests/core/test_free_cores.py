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


def test_own_work_is_not_a_neighbour():
    cores = FreeCores()
    n = len(cores.cpus)
    cores.threads(n)
    _spin(WINDOW_S * 2)  # this process busy on one core the whole window: counted, it would take a core
    assert 1 <= cores.threads(3 * n) <= n
    assert n - cores.free < 0.9, f"own work counted as a neighbour: {cores.free:.2f} free of {n}"
