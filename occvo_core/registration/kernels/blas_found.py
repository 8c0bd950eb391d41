"""Which OpenBLAS numpy's linalg runs on: GICP's kernels call its routines so that a loop compiled whole gives the
bits numpy gives step by step. Found before any kernel is compiled, since the kernels' cache is kept per finding."""

from __future__ import annotations

import ctypes
import os
from pathlib import Path


def numpy_openblas() -> tuple[str, str] | None:
    """(library, symbol prefix) of the OpenBLAS numpy runs on, found among the libraries this process has mapped
    (numpy 2's PyPI wheels bundle scipy-openblas64, numpy 1's openblas64_); None where numpy runs on another BLAS
    (Accelerate, MKL, a distribution's) or OCCVO_LINALG=numba asks for numba's own linear algebra."""
    import numpy.linalg  # noqa: F401 - maps numpy's OpenBLAS into the process

    maps = Path("/proc/self/maps")
    if os.environ.get("OCCVO_LINALG") == "numba" or not maps.exists():
        return None
    for path in sorted({w for w in maps.read_text().split() if "blas" in w.lower() and ".so" in w}):
        for prefix in ("scipy_", ""):
            if hasattr(ctypes.CDLL(path), f"{prefix}dgesv_64_"):
                return path, prefix
    return None


NUMPY_OPENBLAS = numpy_openblas()
