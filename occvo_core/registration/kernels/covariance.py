"""GICP covariances: per-point planes from the grid neighbourhood, and covariances moved rigidly."""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from occvo_core.registration.kernels import CACHE
from occvo_core.registration.kernels.grid import column_masks

PLANE_SLOTS = 4096  # planes remembered a thread (plane_covariances)
MOMENT_STEP = 1 << 16  # a field of _window_moments' packed words


@njit(cache=CACHE, nogil=True, inline="always")
def _null_vector(a00, a01, a02, a11, a12, a22, lam):
    """A unit vector along the cross product of two rows of (A - lam I), the largest of the three (all are parallel
    to the eigenvector of lam when it is a single root); (0, 0, 0) when all vanish."""
    r0x, r0y, r0z = a00 - lam, a01, a02
    r1x, r1y, r1z = a01, a11 - lam, a12
    r2x, r2y, r2z = a02, a12, a22 - lam
    c0x, c0y, c0z = r0y * r1z - r0z * r1y, r0z * r1x - r0x * r1z, r0x * r1y - r0y * r1x
    c1x, c1y, c1z = r0y * r2z - r0z * r2y, r0z * r2x - r0x * r2z, r0x * r2y - r0y * r2x
    c2x, c2y, c2z = r1y * r2z - r1z * r2y, r1z * r2x - r1x * r2z, r1x * r2y - r1y * r2x
    n0, n1, n2 = c0x * c0x + c0y * c0y + c0z * c0z, c1x * c1x + c1y * c1y + c1z * c1z, c2x * c2x + c2y * c2y + c2z * c2z
    if n0 >= n1 and n0 >= n2 and n0 > 0.0:
        s = 1.0 / np.sqrt(n0)
        return c0x * s, c0y * s, c0z * s
    if n1 >= n2 and n1 > 0.0:
        s = 1.0 / np.sqrt(n1)
        return c1x * s, c1y * s, c1z * s
    if n2 > 0.0:
        s = 1.0 / np.sqrt(n2)
        return c2x * s, c2y * s, c2z * s
    return 0.0, 0.0, 0.0


@njit(cache=CACHE, nogil=True, inline="always")
def _smallest_eigenvector(a00, a01, a02, a11, a12, a22):
    """(unit eigenvector of the smallest eigenvalue of a symmetric 3x3 matrix, True) (closed form, no allocation);
    where that eigenvalue is double (a line of voxels, a pole), (unit eigenvector of the largest, along the line,
    False): no normal across a line is the plane's, and any pick would turn with the axes (z, the one a turn keeps,
    lies along a pole)."""
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    q = (a00 + a11 + a22) / 3.0
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    if p < 1e-12 * max(abs(q), 1e-300) or p == 0.0:
        return 0.0, 0.0, 1.0, True  # isotropic: no preferred normal
    b00, b11, b22 = (a00 - q) / p, (a11 - q) / p, (a22 - q) / p
    b01, b02, b12 = a01 / p, a02 / p, a12 / p
    r = (b00 * (b11 * b22 - b12 * b12) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)) / 2.0
    r = min(1.0, max(-1.0, r))
    phi = np.arccos(r) / 3.0
    lam = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)  # the smallest root
    mid = 3.0 * q - lam - (q + 2.0 * p * np.cos(phi))
    if mid - lam > 1e-6 * p:
        nx, ny, nz = _null_vector(a00, a01, a02, a11, a12, a22, lam)
        if nx != 0.0 or ny != 0.0 or nz != 0.0:
            return nx, ny, nz, True
    vx, vy, vz = _null_vector(a00, a01, a02, a11, a12, a22, q + 2.0 * p * np.cos(phi))  # a double smallest root
    return vx, vy, vz, False


@njit(cache=CACHE, nogil=True)
def _window_moments(width):
    """For each occupancy pattern of a column window `width` voxels high (bit b: offset b - width // 2): its count,
    sum of offsets and sum of squared offsets, packed in one word (count + sum * 2^16 + squares * 2^32): the
    moments are linear in the word, so a weighted sum of words is the words of the weighted sums, three fields
    at once."""
    half = width // 2
    table = np.zeros(1 << width, np.int64)
    for bits in range(1 << width):
        for b in range(width):
            if bits >> b & 1:
                d = b - half
                table[bits] += 1 + d * MOMENT_STEP + d * d * MOMENT_STEP * MOMENT_STEP
    return table


@njit(cache=CACHE, nogil=True, inline="always")
def _low_field(word):
    """(the lowest signed 16-bit field of a packed word, the word above it): exact while each field is under 2^15."""
    low = ((word + MOMENT_STEP // 2) & (MOMENT_STEP - 1)) - MOMENT_STEP // 2
    return low, (word - low) >> 16


@njit(cache=CACHE, nogil=True, inline="always")
def _plane_covariance(ijk, shape, radius, epsilon, table, masks, full, seen, solved, cov, n):
    """plane_covariances for point n, into cov."""
    nj = shape[1] + 2 * radius
    k = ijk[n, 2]
    t0 = ti = tii = tj = tij = tjj = 0  # packed sums of the neighbours' moments weighted by 1, di, di^2, dj, ...
    for di in range(-radius, radius + 1):
        # the row's sums over dj first, then weighted by di once (whole numbers: the same totals)
        first = (ijk[n, 0] + radius + di) * nj + ijk[n, 1]
        r0 = r1 = r2 = 0
        for dj in range(-radius, radius + 1):
            w = table[(masks[first + radius + dj] >> k) & full]  # an empty column's word is 0: no branch
            r0 += w
            r1 += dj * w
            r2 += dj * dj * w
        t0 += r0
        ti += di * r0
        tii += di * di * r0
        tj += r1
        tij += di * r1
        tjj += r2
    cnt, rest = _low_field(t0)
    sz, szz = _low_field(rest)
    sx, rest = _low_field(ti)
    sxz = _low_field(rest)[0]
    sy, rest = _low_field(tj)
    syz = _low_field(rest)[0]
    sxx, sxy, syy = _low_field(tii)[0], _low_field(tij)[0], _low_field(tjj)[0]
    nx, ny, nz, plane = 0.0, 0.0, 0.0, False
    if cnt >= 3:  # cnt^2 times the scatter matrix, in whole numbers
        a00, a01, a02 = cnt * sxx - sx * sx, cnt * sxy - sx * sy, cnt * sxz - sx * sz
        a11, a12, a22 = cnt * syy - sy * sy, cnt * syz - sy * sz, cnt * szz - sz * sz
        h = a00 * 0x9E3779B1 + a01 * 0x85EBCA77 + a02 * 0xC2B2AE3D + a11 * 0x27D4EB2F + a12 * 0x165667B1 + a22
        slot = (h ^ (h >> 17)) & (PLANE_SLOTS - 1)
        key = seen[slot]
        if key[0] == a00 and key[1] == a01 and key[2] == a02 and key[3] == a11 and key[4] == a12 and key[5] == a22:
            nx, ny, nz, plane = solved[slot, 0], solved[slot, 1], solved[slot, 2], solved[slot, 3] > 0.0
        else:
            nx, ny, nz, plane = _smallest_eigenvector(
                float(a00), float(a01), float(a02), float(a11), float(a12), float(a22)
            )
            key[0], key[1], key[2], key[3], key[4], key[5] = a00, a01, a02, a11, a12, a22
            solved[slot, 0], solved[slot, 1], solved[slot, 2] = nx, ny, nz
            solved[slot, 3] = 1.0 if plane else 0.0
    # d I + c u u^T: a plane (u its normal) eps along u and 1 across it; a line (u along it) 1 along u and eps
    # across it every way; too few neighbours (u zero): isotropic
    if plane:
        d, c = 1.0, epsilon - 1.0
    elif nx == 0.0 and ny == 0.0 and nz == 0.0:
        d, c = 1.0, 0.0
    else:
        d, c = epsilon, 1.0 - epsilon
    cov[0, 0] = d + c * nx * nx
    cov[1, 1] = d + c * ny * ny
    cov[2, 2] = d + c * nz * nz
    cov[0, 1] = cov[1, 0] = c * nx * ny
    cov[0, 2] = cov[2, 0] = c * nx * nz
    cov[1, 2] = cov[2, 1] = c * ny * nz


@njit(cache=CACHE, nogil=True, parallel=True)
def plane_covariances(ijk, shape, radius, epsilon, parts=1):
    """GICP covariances (Segal et al.): the neighbourhood's plane, as eps along its normal and 1 across it. The plane
    is fitted to the neighbours' grid offsets (whole numbers): its moments are exact, so a frame turned about z by a
    multiple of 90 degrees gets the same planes turned, whatever order its neighbours are met in. The voxels of
    `ijk` are each other's neighbours; each column of the neighbourhood is one look-up of its occupancy
    bits in a table of their moments, so a wider radius costs (2r+1)^2 look-ups, not (2r+1)^3. parts: slices of the
    points run at once (the threads'), the same covariances for any number."""
    n_pts = ijk.shape[0]
    covs = np.empty((n_pts, 3, 3))
    if radius > 4:  # r^2 (2r+1)^3 bounds the packed fields, each under 2^15
        raise ValueError("neighbourhood radii over 4 voxels are not supported")
    width = 2 * radius + 1
    table = _window_moments(width)
    masks = column_masks(ijk, shape, radius)  # padded by the radius: no edge tests
    full = (np.int64(1) << width) - 1
    # a flat or evenly sloped surface repeats its neighbourhood's scatter: each part keeps the last planes it solved
    # in a small table keyed by the scatter's whole numbers; a hit is the same solve's bits
    seen = np.full((parts, PLANE_SLOTS, 6), -1, np.int64)
    solved = np.empty((parts, PLANE_SLOTS, 4))
    for part in prange(parts):
        for n in range(n_pts * part // parts, n_pts * (part + 1) // parts):
            _plane_covariance(ijk, shape, radius, epsilon, table, masks, full, seen[part], solved[part], covs[n], n)
    return covs


@njit(cache=CACHE, nogil=True, parallel=True)
def rotate_covariances(cov, rot):
    """R C R^T for each C (numpy's batched matmul is slow for 3x3)."""
    out = np.empty_like(cov)
    for n in prange(cov.shape[0]):
        for a in range(3):
            t0 = rot[a, 0] * cov[n, 0, 0] + rot[a, 1] * cov[n, 1, 0] + rot[a, 2] * cov[n, 2, 0]
            t1 = rot[a, 0] * cov[n, 0, 1] + rot[a, 1] * cov[n, 1, 1] + rot[a, 2] * cov[n, 2, 1]
            t2 = rot[a, 0] * cov[n, 0, 2] + rot[a, 1] * cov[n, 1, 2] + rot[a, 2] * cov[n, 2, 2]
            for b in range(3):
                out[n, a, b] = t0 * rot[b, 0] + t1 * rot[b, 1] + t2 * rot[b, 2]
    return out


@njit(cache=CACHE, nogil=True, inline="always")
def rigid_motion(rot, trans, g, p0, p1, p2, c, out_pos, out_cov):
    """R p + t into out_pos (3,) and R C R^T into out_cov (3,3) for motion g; c must not be out_cov."""
    for a in range(3):
        out_pos[a] = rot[g, a, 0] * p0 + rot[g, a, 1] * p1 + rot[g, a, 2] * p2 + trans[g, a]
        t0 = rot[g, a, 0] * c[0, 0] + rot[g, a, 1] * c[1, 0] + rot[g, a, 2] * c[2, 0]
        t1 = rot[g, a, 0] * c[0, 1] + rot[g, a, 1] * c[1, 1] + rot[g, a, 2] * c[2, 1]
        t2 = rot[g, a, 0] * c[0, 2] + rot[g, a, 1] * c[1, 2] + rot[g, a, 2] * c[2, 2]
        for b in range(3):
            out_cov[a, b] = t0 * rot[g, b, 0] + t1 * rot[g, b, 1] + t2 * rot[g, b, 2]


@njit(cache=CACHE, nogil=True, parallel=True)
def rigid_motions(pos, cov, rot, trans, group):
    """Each point and covariance moved by the rotation and translation of its group: R p + t, R C R^T (a loop
    closure moves each voxel with the frame that made it; numpy's batched 3x3 products are slow)."""
    out_pos = np.empty_like(pos)
    out_cov = np.empty_like(cov)
    for n in prange(pos.shape[0]):
        rigid_motion(rot, trans, group[n], pos[n, 0], pos[n, 1], pos[n, 2], cov[n], out_pos[n], out_cov[n])
    return out_pos, out_cov


@njit(cache=CACHE, nogil=True)
def scatter(points):
    """3x3 scatter of points about their mean, two passes: numpy's mean over axis 0 of an (n, 3) array alone takes
    longer than all of this."""
    n = points.shape[0]
    mean = np.zeros(3)
    for i in range(n):
        for a in range(3):
            mean[a] += points[i, a]
    mean /= max(n, 1)
    out = np.zeros((3, 3))
    for i in range(n):
        d0, d1, d2 = points[i, 0] - mean[0], points[i, 1] - mean[1], points[i, 2] - mean[2]
        out[0, 0] += d0 * d0
        out[0, 1] += d0 * d1
        out[0, 2] += d0 * d2
        out[1, 1] += d1 * d1
        out[1, 2] += d1 * d2
        out[2, 2] += d2 * d2
    out[1, 0], out[2, 0], out[2, 1] = out[0, 1], out[0, 2], out[1, 2]
    return out
