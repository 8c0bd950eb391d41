"""Numba kernels: the town sampled on the ego-frame Occ3D grid, agent boxes, and the camera visibility pass."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from occvo_core.grid import FREE, OCC3D_GRID

NX, NY, NZ = OCC3D_GRID.shape
LOWER = np.array(OCC3D_GRID.lower)
VOXEL = OCC3D_GRID.voxel_size
D_AZ = 0.007  # ray fan spacing: 0.28 m apart at 40 m, 0.4 m at the grid's corners


@njit(cache=True)
def render_static(R, t, h_base, raise_cm, ground, layers, ox, oy, res, zq, lower, voxel, out):
    """out[i,j,k] = class of the world at ego voxel (i,j,k): object layers first, then the ground slab.

    A voxel is occupied when its vertical extent overlaps an object's [bottom, top] at the raster cell
    under its centre; the ground is a 0.5 m slab below the ground top."""
    nx, ny, nz = out.shape
    w, h = ground.shape
    half = 0.5 * voxel
    for i in range(nx):
        x = lower[0] + (i + 0.5) * voxel
        for j in range(ny):
            y = lower[1] + (j + 0.5) * voxel
            z = lower[2] + 0.5 * voxel
            qx = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
            qy = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
            qz = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
            for k in range(nz):
                if k:  # next voxel up the column
                    qx += R[0, 2] * voxel
                    qy += R[1, 2] * voxel
                    qz += R[2, 2] * voxel
                u = int(math.floor((qx - ox) / res))
                v = int(math.floor((qy - oy) / res))
                lab = 17
                if 0 <= u < w and 0 <= v < h:
                    zr = qz - h_base[u, v]
                    lo = zr - half
                    hi = zr + half
                    for layer in range(1, -1, -1):  # upper layer (crowns, signs) wins over lower
                        if layers[layer, 0, u, v] != 255:
                            b = layers[layer, 1, u, v] * zq
                            tp = layers[layer, 2, u, v] * zq
                            if b < hi and tp > lo:
                                lab = layers[layer, 0, u, v]
                                break
                    if lab == 17:
                        top = raise_cm[u, v] * 0.01
                        if top - 0.5 < hi and top > lo:
                            lab = ground[u, v]
                out[i, j, k] = lab


@njit(cache=True)
def render_boxes(boxes, lower, voxel, out):
    """Oriented boxes (n,16): R (9, box->ego), centre (3), half extents (3), label; voxel centres inside get the label."""
    nx, ny, nz = out.shape
    for b in range(boxes.shape[0]):
        R = boxes[b, 0:9].reshape(3, 3)
        c = boxes[b, 9:12]
        he = boxes[b, 12:15]
        lab = np.uint8(boxes[b, 15])
        ext = np.zeros(3)
        for a in range(3):
            ext[a] = abs(R[a, 0]) * he[0] + abs(R[a, 1]) * he[1] + abs(R[a, 2]) * he[2]
        i0 = max(int(math.floor((c[0] - ext[0] - lower[0]) / voxel)), 0)
        i1 = min(int(math.floor((c[0] + ext[0] - lower[0]) / voxel)), nx - 1)
        j0 = max(int(math.floor((c[1] - ext[1] - lower[1]) / voxel)), 0)
        j1 = min(int(math.floor((c[1] + ext[1] - lower[1]) / voxel)), ny - 1)
        k0 = max(int(math.floor((c[2] - ext[2] - lower[2]) / voxel)), 0)
        k1 = min(int(math.floor((c[2] + ext[2] - lower[2]) / voxel)), nz - 1)
        for i in range(i0, i1 + 1):
            dx = lower[0] + (i + 0.5) * voxel - c[0]
            for j in range(j0, j1 + 1):
                dy = lower[1] + (j + 0.5) * voxel - c[1]
                for k in range(k0, k1 + 1):
                    dz = lower[2] + (k + 0.5) * voxel - c[2]
                    inside = True
                    for a in range(3):
                        if abs(R[0, a] * dx + R[1, a] * dy + R[2, a] * dz) > he[a]:
                            inside = False
                            break
                    if inside:
                        out[i, j, k] = lab


@njit(cache=True)
def _subtract(lo, hi, n, a, b):
    """Remove [a, b] from the sorted disjoint open intervals lo[:n], hi[:n]; return the new count."""
    out = 0
    tmp_lo = np.empty(n + 1)
    tmp_hi = np.empty(n + 1)
    for i in range(n):
        if hi[i] <= a or lo[i] >= b:
            tmp_lo[out] = lo[i]
            tmp_hi[out] = hi[i]
            out += 1
            continue
        if lo[i] < a:
            tmp_lo[out] = lo[i]
            tmp_hi[out] = a
            out += 1
        if hi[i] > b:
            tmp_lo[out] = b
            tmp_hi[out] = hi[i]
            out += 1
    for i in range(out):
        lo[i] = tmp_lo[i]
        hi[i] = tmp_hi[i]
    return out


@njit(cache=True)
def visibility(occupied, cams, lower, voxel, d_az, mask):
    """Mark in `mask` every voxel some camera ray reaches before an occupied voxel (that voxel included).

    cams (n,7): x, y, z, yaw, half horizontal FOV, lowest and highest elevation (rad), ego frame.
    For each camera, rays fan out in vertical planes every d_az rad of azimuth; along each plane a 2-D
    traversal visits the columns in order and keeps the set of still-open elevations as exact intervals
    of tan(elevation). A voxel is seen when the slopes its rectangle subtends meet an open interval; an
    occupied voxel then closes them. Within a column, voxels are visited outwards from the camera height,
    the order in which rays cross them."""
    nx, ny, nz = occupied.shape
    cap = 4 * nx * nz
    lo = np.empty(cap)
    hi = np.empty(cap)
    for c in range(cams.shape[0]):
        cx, cy, cz = cams[c, 0], cams[c, 1], cams[c, 2]
        s_lo, s_hi = math.tan(cams[c, 5]), math.tan(cams[c, 6])
        kc = min(max(int(math.floor((cz - lower[2]) / voxel)), 0), nz - 1)
        n_az = int(math.ceil(2 * cams[c, 4] / d_az)) + 1
        order = np.empty(nz, np.int64)
        m = 0
        for k in range(kc, -1, -1):
            order[m] = k
            m += 1
        for k in range(kc + 1, nz):
            order[m] = k
            m += 1
        top = lower[2] + nz * voxel - cz
        for a in range(n_az):
            az = cams[c, 3] - cams[c, 4] + a * (2 * cams[c, 4]) / (n_az - 1)
            dx, dy = math.cos(az), math.sin(az)
            lo[0] = s_lo
            hi[0] = s_hi
            n = 1
            ix = int(math.floor((cx - lower[0]) / voxel))
            iy = int(math.floor((cy - lower[1]) / voxel))
            sx = 1 if dx > 0 else -1
            sy = 1 if dy > 0 else -1
            if abs(dx) > 1e-12:
                tmx = (lower[0] + (ix + (1 if dx > 0 else 0)) * voxel - cx) / dx
                tdx = voxel / abs(dx)
            else:
                tmx = 1e30
                tdx = 1e30
            if abs(dy) > 1e-12:
                tmy = (lower[1] + (iy + (1 if dy > 0 else 0)) * voxel - cy) / dy
                tdy = voxel / abs(dy)
            else:
                tmy = 1e30
                tdy = 1e30
            r_in = 1e-6
            while 0 <= ix < nx and 0 <= iy < ny and n > 0:
                r_out = max(min(tmx, tmy), 1e-6)
                inv_in = 1.0 / r_in
                inv_out = 1.0 / r_out
                # rays above the grid's top never come back
                s_top = top * inv_in
                if hi[n - 1] > s_top:
                    n = _subtract(lo, hi, n, s_top, 1e30)
                for m in range(nz):
                    if n == 0:
                        break
                    k = order[m]
                    a_lo = lower[2] + k * voxel - cz
                    a_hi = a_lo + voxel
                    smin = a_lo * inv_in if a_lo < 0 else a_lo * inv_out
                    smax = a_hi * inv_out if a_hi < 0 else a_hi * inv_in
                    if smax <= lo[0] or smin >= hi[n - 1]:
                        continue
                    seen = False
                    for i in range(n):
                        if lo[i] < smax and hi[i] > smin:
                            seen = True
                            break
                    if seen:
                        mask[ix, iy, k] = True
                        if occupied[ix, iy, k]:
                            n = _subtract(lo, hi, n, smin, smax)
                r_in = r_out
                if tmx < tmy:
                    ix += sx
                    tmx += tdx
                else:
                    iy += sy
                    tmy += tdy


def visible(grid: np.ndarray, sensors: np.ndarray, lower=LOWER, voxel: float = VOXEL) -> np.ndarray:
    """bool mask of the label grid `grid` (FREE = free): the voxels some ray of `sensors` (rows as `visibility`
    takes them) reaches, the surface hit included."""
    mask = np.zeros(grid.shape, np.bool_)
    visibility(grid != FREE, sensors, np.asarray(lower, np.float64), float(voxel), D_AZ, mask)
    return mask


def empty_grid() -> np.ndarray:
    return np.full((NX, NY, NZ), FREE, np.uint8)


@njit(cache=True)
def nonzero3(grid, value, equal):
    """(N,3) int64 indices, in C order, where grid == value (equal) or grid != value (not equal); argwhere, faster."""
    nx, ny, nz = grid.shape
    n = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if (grid[i, j, k] == value) == equal:
                    n += 1
    out = np.empty((n, 3), np.int64)
    n = 0
    for i in range(nx):
        for j in range(ny):
            for k in range(nz):
                if (grid[i, j, k] == value) == equal:
                    out[n, 0] = i
                    out[n, 1] = j
                    out[n, 2] = k
                    n += 1
    return out


@njit(cache=True)
def horizontal_neighbours(solid, idx):
    """For each voxel idx (N,3), how many of its 8 horizontal neighbours are set in `solid`."""
    nx, ny, _ = solid.shape
    out = np.zeros(idx.shape[0], np.int64)
    for n in range(idx.shape[0]):
        i, j, k = idx[n, 0], idx[n, 1], idx[n, 2]
        c = 0
        for di in range(-1, 2):
            for dj in range(-1, 2):
                if (di or dj) and 0 <= i + di < nx and 0 <= j + dj < ny and solid[i + di, j + dj, k]:
                    c += 1
        out[n] = c
    return out


@njit(cache=True)
def surface_free_voxels(occ_idx, occupied, seen, labels):
    """Visible free voxels face-adjacent to an occupied voxel of occ_idx (N,3, C order), themselves in C order:
    (indices (K,3), class of the first occupied neighbour in occ_idx order)."""
    nx, ny, nz = occupied.shape
    mark = np.zeros(occupied.shape, np.bool_)
    lin = np.empty(6 * occ_idx.shape[0], np.int64)
    lab = np.empty(6 * occ_idx.shape[0], np.uint8)
    n = 0
    for m in range(occ_idx.shape[0]):
        i, j, k = occ_idx[m, 0], occ_idx[m, 1], occ_idx[m, 2]
        for f in range(6):
            a, b, c = i, j, k
            if f == 0:
                a += 1
            elif f == 1:
                a -= 1
            elif f == 2:
                b += 1
            elif f == 3:
                b -= 1
            elif f == 4:
                c += 1
            else:
                c -= 1
            if (
                0 <= a < nx
                and 0 <= b < ny
                and 0 <= c < nz
                and seen[a, b, c]
                and not occupied[a, b, c]
                and not mark[a, b, c]
            ):
                mark[a, b, c] = True
                lin[n] = (a * ny + b) * nz + c
                lab[n] = labels[i, j, k]
                n += 1
    order = np.argsort(lin[:n])
    idx = np.empty((n, 3), np.int64)
    out_lab = np.empty(n, np.uint8)
    for q in range(n):
        v = lin[order[q]]
        idx[q, 0] = v // (ny * nz)
        idx[q, 1] = (v // nz) % ny
        idx[q, 2] = v % nz
        out_lab[q] = lab[order[q]]
    return idx, out_lab
