"""One thread of a process at a time runs kernels on several threads (occvo_core.registration.kernels.use_threads):
libgomp gives every such thread a team of its own, and more team threads than cores make them all sleep at every
barrier. Run in a fresh interpreter, so no thread of the test session owns the team already."""

from __future__ import annotations

import subprocess
import sys

import numba
import pytest

SCRIPT = """
import threading
import numba
from occvo_core.registration.kernels import own_team, use_threads

got = {}
first_asked, release = threading.Event(), threading.Event()

def first():
    use_threads(2)
    got["first"] = numba.get_num_threads()
    first_asked.set()
    release.wait()

def ask(name, threads):
    use_threads(threads)
    got[name] = (numba.get_num_threads(), own_team())

a = threading.Thread(target=first)
a.start()
first_asked.wait()
for name, threads in (("second", 2), ("one", 1)):
    t = threading.Thread(target=ask, args=(name, threads))
    t.start()
    t.join()
release.set()
a.join()
t = threading.Thread(target=ask, args=("after", 2))
t.start()
t.join()
print(got)
"""


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="one core: no kernel runs on several threads here")
def test_only_one_thread_at_a_time_runs_kernels_on_several():
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120, check=True)
    got = eval(out.stdout.strip().splitlines()[-1])  # noqa: S307 - our own script's dict of ints and bools
    assert got["first"] == 2
    assert got["second"] == (1, False)  # the first thread is alive: this one runs on one
    assert got["one"] == (1, False)  # asking for one claims nothing
    assert got["after"] == (2, True)  # the first ended (its team with it): the next to ask has several


def test_kernel_threads_leave_torchs_thread_count_alone():
    """numba's OpenMP start-up used to reset torch's count to all cores, so a model's predictions (whose last bits
    depend on it) changed with whether registration had run yet in the process."""
    script = (
        "import torch\nfrom occvo_core.registration.kernels import use_threads\n"
        "torch.set_num_threads(1)\ntorch.get_num_threads()\nuse_threads(0)\nprint(torch.get_num_threads())"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip().splitlines()[-1] == "1"
