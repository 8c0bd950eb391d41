"""Rigid motions inside kernels, each with the bits of the numpy expression it replaces."""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import njit

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.numpy_blas import matmul, norm


@njit(cache=CACHE, nogil=True)
def rotvec_matrix(rotvec):
    """Rotation.from_rotvec(rotvec).as_matrix(), bit for bit (scipy's quaternion formulas, in its operation order),
    without scipy's per-call cost."""
    x, y, z = rotvec[0], rotvec[1], rotvec[2]
    angle = math.sqrt(x * x + y * y + z * z)
    if angle <= 1e-3:  # scipy's Taylor series of sin(angle / 2) / angle
        a2 = angle * angle
        scale = 0.5 - a2 / 48 + a2 * a2 / 3840
    else:
        scale = math.sin(angle / 2) / angle
    qx, qy, qz, qw = scale * x, scale * y, scale * z, math.cos(angle / 2)
    x2, y2, z2, w2 = qx * qx, qy * qy, qz * qz, qw * qw
    xy, zw, xz, yw, yz, xw = qx * qy, qz * qw, qx * qz, qy * qw, qy * qz, qx * qw
    m = np.empty((3, 3))
    m[0, 0], m[0, 1], m[0, 2] = x2 - y2 - z2 + w2, 2 * (xy - zw), 2 * (xz + yw)
    m[1, 0], m[1, 1], m[1, 2] = 2 * (xy + zw), -x2 + y2 - z2 + w2, 2 * (yz - xw)
    m[2, 0], m[2, 1], m[2, 2] = 2 * (xz - yw), 2 * (yz + xw), -x2 - y2 + z2 + w2
    return m


@njit(cache=CACHE, nogil=True)
def se3_exp_left(delta, pose):
    """exp(delta) @ pose for delta = (rotation vector, translation)."""
    step = np.eye(4)
    step[:3, :3] = rotvec_matrix(delta[:3])
    step[:3, 3] = delta[3:]
    return matmul(step, pose)


@njit(cache=CACHE)
def _numpy_arccos(x):
    """np.arccos(x) itself: numpy may take it from SIMD code whose last bit differs from the C library's."""
    with numba.objmode(y="float64"):
        y = float(np.arccos(x))
    return y


@njit(cache=CACHE, nogil=True)
def moved_beyond(pose, since, since_inv, reach, limit):
    """Whether a point within `reach` of the origin may have moved more than `limit` from pose `since` (inverse
    since_inv) to pose, by the bound |t| + angle * (reach + |t since|) that numpy gives. The angle is the C library's
    arccos, within 2 ulps of numpy's: numpy's is asked only when the bound over 4 ulps either side straddles the
    limit (the bound grows with the angle)."""
    step = matmul(pose, since_inv)
    t, lever = norm(step[:3, 3]), reach + norm(since[:3, 3])
    cos = min(max((step[0, 0] + step[1, 1] + step[2, 2] - 1.0) / 2.0, -1.0), 1.0)  # numpy's trace: in order
    lo = hi = math.acos(cos)
    for _ in range(4):
        lo, hi = np.nextafter(lo, -np.inf), np.nextafter(hi, np.inf)
    if t + lo * lever > limit:
        return True
    if not t + hi * lever > limit:
        return False
    return t + _numpy_arccos(cos) * lever > limit
