"""numpy's own BLAS and LAPACK (its bundled OpenBLAS), bound for kernels: a GICP loop compiled whole must give the
bits numpy gave it step by step, and numba's np.linalg calls scipy's OpenBLAS, another build whose kernels may round
otherwise. Each function here makes the call numpy makes for the same expression; where numpy runs on another BLAS
(or OCCVO_LINALG=numba), numba's own linear algebra serves instead."""

from __future__ import annotations

import warnings

import llvmlite.binding
import numpy as np
from numba import njit, types
from numba.core import cgutils
from numba.extending import intrinsic

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.blas_found import NUMPY_OPENBLAS

if NUMPY_OPENBLAS is None:
    # Elsewhere (numpy on Accelerate, MKL, a distribution's BLAS) numba's own linear algebra serves: poses then may
    # differ from a numpy-wheel build in the last bits, the same on any thread count.
    warnings.warn("numpy's linalg runs on no bundled OpenBLAS: GICP's kernels use numba's linear algebra", stacklevel=1)
else:
    _lib, _pre = NUMPY_OPENBLAS
    llvmlite.binding.load_library_permanently(_lib)
    _p, _i, _d, _e = types.voidptr, types.int64, types.float64, types.int32  # _e: a CBLAS enum
    _dgesv = types.ExternalFunction(f"{_pre}dgesv_64_", types.void(_p, _p, _p, _p, _p, _p, _p, _p))
    _ddot = types.ExternalFunction(f"{_pre}cblas_ddot64_", _d(_i, _p, _i, _p, _i))
    _dgemm = types.ExternalFunction(
        f"{_pre}cblas_dgemm64_", types.void(_e, _e, _e, *(_i,) * 3, _d, _p, _i, _p, _i, _d, _p, _i)
    )
_ROW_MAJOR, _NO_TRANS = 101, 111  # CBLAS's enums


@intrinsic
def _address(typingctx, arr):
    """The data pointer of a contiguous array."""

    def codegen(context, builder, sig, args):
        data = context.make_array(sig.args[0])(context, builder, args[0]).data
        return builder.bitcast(data, cgutils.voidptr_t)

    return types.voidptr(arr), codegen


@njit(cache=CACHE, nogil=True)
def _gesv(a, b):
    """numpy's gesv call: a (n, n) copied in Fortran order, b (n, k) Fortran order, overwritten by the solution."""
    n = a.shape[0]
    fa = np.empty(n * n)
    for i in range(n):
        for j in range(n):
            fa[j * n + i] = a[i, j]
    ints = np.array([n, b.shape[0] * b.shape[1] // n, 0])  # n, nrhs, info
    ipiv = np.empty(n, np.int64)
    n_, nrhs, info = _address(ints[0:1]), _address(ints[1:2]), _address(ints[2:3])
    _dgesv(n_, nrhs, _address(fa), n_, _address(ipiv), _address(b), n_, info)
    return ints[2]


@njit(cache=CACHE, nogil=True)
def solve(a, b):
    """np.linalg.solve(a, b) for a vector b."""
    x = b.copy()
    if _gesv(a, x.reshape((-1, 1))) != 0:
        raise ValueError("singular matrix")
    return x


@njit(cache=CACHE, nogil=True)
def inv(a):
    """np.linalg.inv(a) (numpy solves a x = I)."""
    n = a.shape[0]
    fb = np.eye(n)
    if _gesv(a, fb) != 0:
        raise ValueError("singular matrix")
    return fb.T.copy()  # fb holds the inverse in Fortran order


@njit(cache=CACHE, nogil=True)
def matmul(a, b):
    """a @ b for C-contiguous matrices (numpy's row-major gemm call)."""
    m, k, n = a.shape[0], a.shape[1], b.shape[1]
    out = np.empty((m, n))
    _dgemm(_ROW_MAJOR, _NO_TRANS, _NO_TRANS, m, n, k, 1.0, _address(a), k, _address(b), n, 0.0, _address(out), n)
    return out


@njit(cache=CACHE, nogil=True)
def norm(x):
    """np.linalg.norm(x) of a vector: sqrt(x.dot(x)), numpy's dot adding BLAS's ddot to 0."""
    c = np.ascontiguousarray(x)
    return np.sqrt(0.0 + _ddot(c.shape[0], _address(c), 1, _address(c), 1))


@njit(cache=CACHE, nogil=True)
def _numba_solve(a, b):
    return np.linalg.solve(a, b)


@njit(cache=CACHE, nogil=True)
def _numba_inv(a):
    return np.linalg.inv(a)


@njit(cache=CACHE, nogil=True)
def _numba_matmul(a, b):
    return a @ b


@njit(cache=CACHE, nogil=True)
def _numba_norm(x):
    c = np.ascontiguousarray(x)
    return np.sqrt(np.dot(c, c))


if NUMPY_OPENBLAS is None:
    solve, inv, matmul, norm = _numba_solve, _numba_inv, _numba_matmul, _numba_norm
