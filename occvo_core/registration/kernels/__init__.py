"""Compiled inner loops of the registration boxes, one module per concept. Every frame lives on a 0.4 m grid, so
neighbour search is a dense-array lookup, not a tree.

The parallel kernels give the same bits on any number of threads: sums are taken over fixed slices and added in
order, and whatever depends on order (new row numbers, grid cells two voxels share) is done serially afterwards."""

from __future__ import annotations

import os

import numba

if "NUMBA_THREADING_LAYER" not in os.environ:
    # streams registered side by side in threads of one worker launch parallel kernels at once: numba's default
    # fallback (workqueue) would abort on that, OpenMP and TBB take it (the variable survives numba's config reloads)
    os.environ["NUMBA_THREADING_LAYER"] = numba.config.THREADING_LAYER = "threadsafe"

if "OMP_WAIT_POLICY" not in os.environ and "GOMP_SPINCOUNT" not in os.environ:
    # a kernel thread that finds no work sleeps at once instead of spinning for its next region (OpenMP's default
    # spins ~0.3 ms): beside a busy neighbour on 2 cores, spinning threads took the core the other thread's slice
    # waited for, and two-thread kernels ran 2.5-8x slower than one thread. Read when libgomp loads, at the first
    # parallel kernel, so set here at import (benchmarks/registration.py --neighbour-load measures it)
    os.environ["OMP_WAIT_POLICY"] = "PASSIVE"

CACHE = True  # compiled kernels are kept on disk: a worker's start does not wait for numba
CHUNKS = 16  # fixed slices of parallel loops (see above)
MODULES = ("grid", "sources", "covariance", "nearest", "gicp", "clusters", "voxel_pfilter", "map_window", "map_rows")


def use_threads(threads: int) -> None:
    """Kernel threads for calls from this Python thread: 0 = all cores (numba's thread count is per thread)."""
    most = numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(most if threads <= 0 else min(threads, most))
