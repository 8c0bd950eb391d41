"""IdleTeam with real numba OpenMP threads: the threads a kernel team leaves spinning make way, then come back; the
workers' short interpreter-lock turns."""

from __future__ import annotations

import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
import pytest

from occvo_core.registration.kernels.covariance import rotate_covariances
from occvo_services.local import InProcessService
from occvo_services.os_tuning import GIL_SWITCH_S, IdleTeam, may_raise_to, name_os_thread, short_gil_turns


def _nice(tid: int) -> int:
    return os.getpriority(os.PRIO_PROCESS, tid)


def test_a_kernel_teams_spinning_threads_are_lowered_after_its_kernels_and_raised_before_the_next():
    """After a parallel kernel run from a thread on two cores, lower() drops the OpenMP thread it leaves spinning
    (named after it) to niceness 19 and leaves the thread itself alone; restore() puts it back at the thread's own."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("one core: a kernel team has no OpenMP threads besides its own")

    def in_team():
        name_os_thread("idle-team-test")
        numba.set_num_threads(2)
        rotate_covariances(np.zeros((4096, 3, 3)), np.eye(3))
        idle = IdleTeam()
        idle.lower(2)
        lowered = {t: _nice(t) for t in idle.tids}
        me = threading.get_native_id()
        mine = _nice(me)
        idle.restore()
        return idle.active, numba.threading_layer(), me, mine, lowered, {t: _nice(t) for t in idle.tids}

    with ThreadPoolExecutor(1) as team:
        active, layer, me, mine, lowered, restored = team.submit(in_team).result()
    if not may_raise_to(mine):
        assert active is False and lowered == {}  # it could not raise them back: it does not lower them
        return
    assert layer == "omp", "the team threads are found by the name they inherit from libgomp's master thread"
    assert active and lowered and me not in lowered, lowered
    assert set(lowered.values()) == {19} and set(restored.values()) == {mine}


def test_short_gil_turns_sets_the_process_switch_interval_and_returns_the_one_before():
    before = sys.getswitchinterval()
    try:
        assert short_gil_turns(0.002) == before
        assert sys.getswitchinterval() == pytest.approx(0.002)
        assert short_gil_turns() == pytest.approx(0.002)
        assert sys.getswitchinterval() == pytest.approx(GIL_SWITCH_S)
    finally:
        sys.setswitchinterval(before)
    assert GIL_SWITCH_S < 0.005  # shorter than Python's default, or the workers gain nothing


def test_an_in_process_service_takes_the_workers_turns_while_it_runs_and_gives_the_process_its_own_back():
    before = sys.getswitchinterval()
    with InProcessService():
        assert sys.getswitchinterval() == pytest.approx(GIL_SWITCH_S)
    assert sys.getswitchinterval() == before
