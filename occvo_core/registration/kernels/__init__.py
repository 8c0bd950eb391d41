"""Compiled inner loops of the registration boxes, one module per concept. Every frame lives on a 0.4 m grid, so
neighbour search is a dense-array lookup, not a tree.

The parallel kernels give the same bits on any number of threads: sums are taken over fixed slices and added in
order, and whatever depends on order (new row numbers, grid cells two voxels share) is done serially afterwards."""

from __future__ import annotations

import os

import numba

from occvo_core.free_cores import FREE_CORES

if "NUMBA_THREADING_LAYER" not in os.environ:
    # streams registered side by side in threads of one worker launch parallel kernels at once: numba's default
    # fallback (workqueue) would abort on that, OpenMP and TBB take it (the variable survives numba's config reloads)
    os.environ["NUMBA_THREADING_LAYER"] = numba.config.THREADING_LAYER = "threadsafe"

CACHE = True  # compiled kernels are kept on disk: a worker's start does not wait for numba
CHUNKS = 16  # fixed slices of parallel loops (see above)
MODULES = ("grid", "sources", "covariance", "nearest", "gicp", "clusters", "voxel_pfilter", "map_window", "map_rows")


def use_threads(threads: int) -> None:
    """Kernel threads for calls from this Python thread: 0 = the cores other processes leave free (numba's thread
    count is per thread)."""
    most = numba.config.NUMBA_NUM_THREADS
    numba.set_num_threads(FREE_CORES.threads(most) if threads <= 0 else min(threads, most))
