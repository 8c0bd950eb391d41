"""Compiled inner loops of the registration boxes, one module per concept. Every frame lives on a 0.4 m grid, so
neighbour search is a dense-array lookup, not a tree.

The parallel kernels give the same bits on any number of threads: sums are taken over fixed slices and added in
order, and whatever depends on order (new row numbers, grid cells two voxels share) is done serially afterwards."""

from __future__ import annotations

import hashlib
import os
import sys
import threading
from pathlib import Path

import numba

from occvo_core.free_cores import FREE_CORES
from occvo_core.registration.kernels.blas_found import NUMPY_OPENBLAS

if "NUMBA_THREADING_LAYER" not in os.environ:
    # streams registered side by side in threads of one worker launch parallel kernels at once: numba's default
    # fallback (workqueue) would abort on that, OpenMP and TBB take it (the variable survives numba's config reloads)
    os.environ["NUMBA_THREADING_LAYER"] = numba.config.THREADING_LAYER = "threadsafe"


def _cache_dir() -> str:
    """numba keys a cached kernel by its own file only, so one that inlines a helper from another file would keep the
    old helper after a change to it alone (a `git pull`): the kernels are cached in a directory of their own for each
    version of the registration package's sources and linear algebra (under NUMBA_CACHE_DIR when set, else beside the sources)."""
    root = Path(__file__).resolve().parents[1]
    linalg = str(NUMPY_OPENBLAS).encode()  # a kernel compiled against numpy's OpenBLAS calls it by name
    sources = b"".join(f.read_bytes() for f in sorted(root.rglob("*.py")))
    digest = hashlib.blake2b(sources + linalg, digest_size=8).hexdigest()
    base = os.environ.get("NUMBA_CACHE_DIR") or str(Path(__file__).parent / "__pycache__")
    name = f"occvo-kernels-{digest}"
    return base if Path(base).name == name else str(Path(base) / name)  # a worker inherits its parent's


os.environ["NUMBA_CACHE_DIR"] = numba.config.CACHE_DIR = _cache_dir()  # the variable survives config reloads
CACHE = True  # compiled kernels are kept on disk: a worker's start does not wait for numba
CHUNKS = 16  # fixed slices of parallel loops (see above)
MODULES = (
    "turns",
    "grid",
    "sources",
    "covariance",
    "nearest",
    "gicp",
    "numpy_blas",
    "se3",
    "gicp_loop",
    "clusters",
    "voxel_pfilter",
    "row_blocks",
    "map_window",
    "map_rows",
)


_team_thread: list[threading.Thread | None] = [None]  # the one thread of this process whose kernels run on several
_team_lock = threading.Lock()


def use_threads(threads: int) -> None:
    """Kernel threads for calls from this Python thread: 0 = the cores other processes leave free (numba's thread
    count is per thread). Only one thread of a process at a time runs kernels on several threads: each keeps an
    OpenMP team of its own, and once a process holds more team threads than cores, libgomp has them all sleep at
    every barrier instead of spinning, and every parallel kernel then waits for its threads to wake (several ms a
    frame at 2 Hz). The first thread to ask for several keeps them until it ends; others run on one."""
    most = numba.config.NUMBA_NUM_THREADS
    n = FREE_CORES.threads(most) if threads <= 0 else min(threads, most)
    torch = sys.modules.get("torch")  # numba's OpenMP start-up resets torch's thread count (one libgomp): kept
    before = torch.get_num_threads() if torch else 0
    numba.set_num_threads(n if n == 1 or own_team() else 1)
    if torch and torch.get_num_threads() != before:
        torch.set_num_threads(before)


def own_team() -> bool:
    """Whether the calling thread is the one whose kernels may run on several threads; it becomes it when no live
    thread is."""
    me = threading.current_thread()
    with _team_lock:
        if _team_thread[0] is None or not _team_thread[0].is_alive():
            _team_thread[0] = me
        return _team_thread[0] is me
