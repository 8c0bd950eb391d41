"""GICP's loop compiled whole keeps numpy's bits: its linear algebra is numpy's own, and a nearest point kept across
iterations is the one a fresh search would find."""

import numpy as np

from occvo_core.registration.kernels import numpy_blas
from occvo_core.registration.kernels.nearest import nearest_within
from occvo_core.registration.kernels.nearest_bound import nearest_bounded, still_nearest
from occvo_core.registration.kernels.se3 import rotvec_matrix


def test_kernels_linear_algebra_gives_numpys_bits():
    rng = np.random.default_rng(0)
    naive_differs = 0
    for _ in range(2000):
        a = rng.normal(size=(6, 6))
        h, g = a @ a.T + 1e-9 * np.eye(6), rng.normal(size=6) * 10 ** rng.uniform(-6, 3)
        assert np.array_equal(numpy_blas.solve(h, -g), np.linalg.solve(h, -g))
        p, q = np.eye(4), np.eye(4)
        p[:3, :3], p[:3, 3] = rotvec_matrix(rng.normal(size=3)), rng.normal(size=3) * 30
        q[:3, :3], q[:3, 3] = rotvec_matrix(rng.normal(size=3) * 0.01), rng.normal(size=3)
        assert np.array_equal(numpy_blas.inv(p), np.linalg.inv(p))
        assert np.array_equal(numpy_blas.matmul(p, q), p @ q)
        assert numpy_blas.norm((p @ q)[:3, 3]) == np.linalg.norm((p @ q)[:3, 3])
        naive_differs += not np.array_equal(np.einsum("ik,kj->ij", p, q), p @ q)
    assert naive_differs > 0  # the comparisons above can tell one rounding from another


def test_a_kept_nearest_point_is_the_one_a_fresh_search_finds():
    """nearest_bounded answers as nearest_within does and bounds every other point; still_nearest answers for a
    moved query only when a fresh search gives the same point and the same squared distance, and mostly does."""
    rng = np.random.default_rng(5)
    voxel, radius, max_d2 = 0.4, 2, 0.6**2
    pts = np.concatenate([rng.uniform(-3, 3, (1500, 3)), rng.normal(0, 0.3, (300, 3))])
    usable = rng.random(len(pts)) < 0.9
    cells = np.floor(pts / voxel).astype(np.int64)
    origin = cells.min(axis=0) - radius
    dims = cells.max(axis=0) - origin + 1 + radius
    grid = np.full(int(np.prod(dims)), -1, np.int64)
    for n, (i, j, k) in enumerate(cells - origin):
        grid[(i * dims[1] + j) * dims[2] + k] = n
    held = np.flatnonzero(np.isin(np.arange(len(pts)), grid) & usable)
    gaps = np.empty((3, 2 * radius + 1))
    kept = asked = 0
    for q in np.concatenate([rng.uniform(-3.5, 3.5, (3000, 3)), rng.normal(0, 0.3, (500, 3))]):
        m, d2, bound2 = nearest_bounded(q, pts, grid, origin, dims, voxel, radius, usable, max_d2, gaps)
        m0, d0 = nearest_within(q, pts, grid, origin, dims, voxel, radius, usable, max_d2)
        if d0 <= max_d2 or d2 <= max_d2:
            assert (m, d2) == (m0, d0)
        others = np.linalg.norm(pts[held[held != m]] - q, axis=1)
        assert bound2 <= max_d2 and (bound2 == 0 or others.min() >= np.sqrt(bound2) - 1e-12)
        moved = q + rng.normal(size=3) * 10 ** rng.uniform(-4, -0.5)
        d_kept = still_nearest(moved, pts, m, q, bound2, max_d2)
        if m >= 0 and bound2 > 0:
            asked += 1
        if d_kept >= 0:
            kept += 1
            assert (m, d_kept) == nearest_within(moved, pts, grid, origin, dims, voxel, radius, usable, max_d2)
    assert kept > asked / 2 > 500


def test_search_skip_decides_as_numpys_arithmetic_at_the_limit():
    """moved_beyond takes the C library's arccos, which may differ from numpy's in the last bit: at a limit equal to
    numpy's bound, or one ulp either side, it must still decide as numpy's arithmetic does."""
    from occvo_core.registration.gicp import rotation_angle
    from occvo_core.registration.kernels.se3 import moved_beyond

    rng = np.random.default_rng(2)
    for _ in range(200):
        since, pose = np.eye(4), np.eye(4)
        since[:3, :3], since[:3, 3] = rotvec_matrix(rng.normal(size=3)), rng.normal(size=3) * 20
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = rotvec_matrix(rng.normal(size=3) * 1e-3), rng.normal(size=3) * 1e-2
        pose = step @ since
        since_inv = np.linalg.inv(since)
        reach = float(rng.uniform(5, 60))
        s = pose @ since_inv
        bound = float(np.linalg.norm(s[:3, 3]) + rotation_angle(s[:3, :3]) * (reach + np.linalg.norm(since[:3, 3])))
        for limit in (np.nextafter(bound, -np.inf), bound, np.nextafter(bound, np.inf)):
            assert moved_beyond(pose, since, since_inv, reach, limit) == (bound > limit)


_FALLBACK = """
import warnings
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    from occvo_core.registration import kernels
    from occvo_core.registration.kernels import blas_found, numpy_blas
assert blas_found.NUMPY_OPENBLAS is None and numpy_blas.solve is numpy_blas._numba_solve
assert any("numba's linear algebra" in str(w.message) for w in caught), [str(w.message) for w in caught]
print(kernels.numba.config.CACHE_DIR)
"""


def test_numpy_on_another_blas_takes_numbas_linear_algebra_in_a_cache_of_its_own():
    """Where numpy runs on no bundled OpenBLAS (Accelerate, MKL; forced here by OCCVO_LINALG=numba) the kernels take
    numba's linear algebra, said in one warning, compiled into a kernel cache of their own (a cached kernel calls
    the OpenBLAS it was built against by name); it answers as numpy does but for the last bits. A whole registration
    on it: two synthetic frames, poses within 1e-6 of this build's (checked by hand: 2 minutes of compiling)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    from occvo_core.registration import kernels

    root = str(Path(__file__).resolve().parents[2])
    path = os.pathsep.join(p for p in (root, os.environ.get("PYTHONPATH")) if p)
    env = {**os.environ, "OCCVO_LINALG": "numba", "PYTHONPATH": path}
    env.pop("NUMBA_CACHE_DIR")  # the package set it for this process: the child derives its own
    out = subprocess.run([sys.executable, "-c", _FALLBACK], env=env, check=True, capture_output=True, text=True)
    assert Path(out.stdout.strip()).name != Path(kernels.numba.config.CACHE_DIR).name

    rng = np.random.default_rng(1)
    for _ in range(200):
        a = rng.normal(size=(6, 6))
        h, g = a @ a.T + 1e-3 * np.eye(6), rng.normal(size=6)
        assert np.allclose(numpy_blas._numba_solve(h, -g), np.linalg.solve(h, -g), rtol=1e-9, atol=1e-12)
        p, q = rng.normal(size=(4, 4)) + 4 * np.eye(4), rng.normal(size=(4, 4))
        assert np.allclose(numpy_blas._numba_inv(p), np.linalg.inv(p), rtol=1e-9, atol=1e-12)
        assert np.allclose(numpy_blas._numba_matmul(p, q), p @ q, rtol=1e-12, atol=1e-12)
        assert np.isclose(numpy_blas._numba_norm((p @ q)[:3, 3]), np.linalg.norm((p @ q)[:3, 3]), rtol=1e-12)
