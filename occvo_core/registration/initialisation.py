"""First-motion guess without ground truth: correlate bird's-eye views of the static vertical structure.

Geometry-only ICP slides along roads when the car starts fast (metres in the first frame);
buildings, vegetation, poles and barriers seen from above pin down x, y and yaw in one FFT per yaw."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation

STRUCTURE_CLASSES = np.array([1, 8, 15, 16])  # barrier, traffic cone, manmade, vegetation


def _bev(points: np.ndarray, labels: np.ndarray, res: float, size: int) -> np.ndarray:
    keep = np.isin(labels, STRUCTURE_CLASSES)
    ij = np.floor(points[keep, :2] / res).astype(np.int64) + size // 2
    inside = np.all((ij >= 0) & (ij < size), axis=1)
    img = np.zeros((size, size))
    np.add.at(img, (ij[inside, 0], ij[inside, 1]), 1.0)
    img = np.minimum(img, 4.0)  # a tall wall should not outweigh the rest of the scene
    return gaussian_filter(img, 1.0)


def bev_first_motion(
    prev_points: np.ndarray,
    prev_labels: np.ndarray,
    points: np.ndarray,
    labels: np.ndarray,
    *,
    search_radius_m: float,
    yaw_steps_deg: tuple[float, ...],
    res: float = 0.8,
) -> tuple[np.ndarray, float]:
    """Relative motion (4x4, current ego -> previous ego) maximising BEV overlap, and its normalised score."""
    size = int(2 ** np.ceil(np.log2(2 * 60.0 / res)))
    ref_img = _bev(prev_points, prev_labels, res, size)
    ref, ref_norm = np.fft.rfft2(ref_img), np.sqrt((ref_img**2).sum())
    limit = int(search_radius_m / res)
    best = (-np.inf, 0.0, 0, 0)
    for yaw_deg in yaw_steps_deg:
        yaw = np.deg2rad(yaw_deg)
        c, s = np.cos(yaw), np.sin(yaw)
        rotated = points[:, :2] @ np.array([[c, s], [-s, c]])
        img = _bev(rotated, labels, res, size)
        corr = _shifts(ref * np.conj(np.fft.rfft2(img)), size, limit)
        i, j = np.unravel_index(np.argmax(corr), corr.shape)
        score = corr[i, j] / max(ref_norm * np.sqrt((img**2).sum()), 1e-12)
        if score > best[0]:
            best = (score, yaw, i - limit, j - limit)
    score, yaw, di, dj = best
    return _planar_motion(yaw, di * res, dj * res), float(score)


def _shifts(cross_spectrum: np.ndarray, size: int, limit: int) -> np.ndarray:
    """The circular cross-correlation of two size x size images at shifts -limit..limit (row 0: shift -limit)."""
    corr = np.fft.irfft2(cross_spectrum, s=(size, size))
    return np.roll(corr, (limit, limit), axis=(0, 1))[: 2 * limit + 1, : 2 * limit + 1]


def _planar_motion(yaw: float, x: float, y: float) -> np.ndarray:
    motion = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    motion[:2, :2] = [[c, -s], [s, c]]
    motion[:2, 3] = (x, y)
    return motion


# semantic_bev_motion's channels: road, other flat and sidewalk, terrain, built structure, vegetation
_MOTION_CHANNELS = ((11,), (12, 13), (14,), (1, 8, 15), (16,))
_MOTION_RES, _MOTION_SIZE = 0.8, 128  # 102 m: the 80 m grid and its moves without wrapping round


def _channel_cells(points: np.ndarray, labels: np.ndarray) -> list[np.ndarray]:
    """Per channel, the x-y centres of its occupied BEV cells (a column counts once)."""
    out = []
    for classes in _MOTION_CHANNELS:
        ij = np.floor(points[np.isin(labels, classes), :2] / _MOTION_RES).astype(np.int64) + (1 << 20)
        keys = np.unique(ij[:, 0] << 21 | ij[:, 1])  # one int64 a cell: a 1-D sort, not a row sort
        out.append(
            np.stack([(keys >> 21) - (1 << 20), (keys & ((1 << 21) - 1)) - (1 << 20)], axis=1) * _MOTION_RES
            + 0.5 * _MOTION_RES
        )
    return out


def _channel_spectra(cells: list[np.ndarray], yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, s], [-s, c]])
    images = np.zeros((len(cells), _MOTION_SIZE * _MOTION_SIZE))
    for image, xy in zip(images, cells):
        ij = np.floor(xy @ rot / _MOTION_RES).astype(np.int64) + _MOTION_SIZE // 2
        ij = ij[np.all((ij >= 0) & (ij < _MOTION_SIZE), axis=1)]
        image[ij[:, 0] * _MOTION_SIZE + ij[:, 1]] = 1.0
    return np.fft.rfft2(images.reshape(len(cells), _MOTION_SIZE, _MOTION_SIZE))


def _band_pass() -> np.ndarray:
    """|H|^2 of a blur (1 cell) less its own blur (3 cells): class boundaries count, the inside of a road does not."""
    f0 = np.fft.fftfreq(_MOTION_SIZE)[:, None]
    f1 = np.fft.rfftfreq(_MOTION_SIZE)[None, :]
    w2 = (2 * np.pi) ** 2 * (f0**2 + f1**2)
    h = np.exp(-0.5 * w2) * (1.0 - np.exp(-0.5 * 9.0 * w2))
    return h**2


_BAND_PASS = _band_pass()


def semantic_bev_motion(
    prev_points: np.ndarray,
    prev_labels: np.ndarray,
    points: np.ndarray,
    labels: np.ndarray,
    *,
    guess: np.ndarray,
    search_radius_m: float,
    yaw_deg: float,
    step_deg: float,
    prior_sigma_m: float,
) -> np.ndarray:
    """Relative motion (4x4, current ego -> previous ego) near `guess` that best overlays the two frames' bird's-eye
    views, class by class (road, sidewalk, terrain, structure, vegetation edges): yaw within +-yaw_deg of the
    guess's, x-y within search_radius_m, with a Gaussian prior of prior_sigma_m on the x-y move."""
    moved = points @ guess[:3, :3].T + guess[:3, 3]
    ref = _channel_spectra(_channel_cells(prev_points, prev_labels), 0.0) * _BAND_PASS
    cells = _channel_cells(moved, labels)
    limit = int(search_radius_m / _MOTION_RES)
    offsets = np.arange(-limit, limit + 1) * _MOTION_RES
    prior = np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * prior_sigma_m**2))
    best = (-np.inf, 0.0, 0, 0)
    for yaw in np.deg2rad(np.arange(-yaw_deg, yaw_deg + 1e-9, step_deg)):
        corr = _shifts((ref * np.conj(_channel_spectra(cells, yaw))).sum(axis=0), _MOTION_SIZE, limit) * prior
        i, j = np.unravel_index(np.argmax(corr), corr.shape)
        if corr[i, j] > best[0]:
            best = (corr[i, j], yaw, i - limit, j - limit)
    _, yaw, di, dj = best
    return _planar_motion(yaw, di * _MOTION_RES, dj * _MOTION_RES) @ guess


def ground_height_correction(
    map_ground: np.ndarray, frame_ground: np.ndarray, centre: np.ndarray, cell_m: float = 0.8, min_cells: int = 30
) -> np.ndarray | None:
    """World -> world correction that puts a frame's ground points (world frame) on the map's ground: a height
    shift and a tilt about `centre`, from a plane fitted robustly to the per x-y cell differences of mean ground
    height. The bird's-eye search finds x, y and yaw only; over a long drive, height and pitch drift too.
    None when fewer than min_cells cells hold both."""

    def cell_heights(points):
        ij = np.floor(points[:, :2] / cell_m).astype(np.int64)
        keys, inverse = np.unique((ij[:, 0] + (1 << 30)) * (1 << 31) + ij[:, 1] + (1 << 30), return_inverse=True)
        inverse = inverse.reshape(-1)
        return keys, np.bincount(inverse, points[:, 2]) / np.bincount(inverse)

    if len(map_ground) == 0 or len(frame_ground) == 0:
        return None
    map_keys, map_z = cell_heights(map_ground)
    frame_keys, frame_z = cell_heights(frame_ground)
    common, mi, fi = np.intersect1d(map_keys, frame_keys, return_indices=True)
    if len(common) < min_cells:
        return None
    xy = np.stack([common // (1 << 31) - (1 << 30), common % (1 << 31) - (1 << 30)], axis=1) * cell_m + 0.5 * cell_m
    xy = xy - centre[:2]
    dz = map_z[mi] - frame_z[fi]
    design = np.column_stack([np.ones(len(dz)), xy])
    keep = np.ones(len(dz), bool)
    for _ in range(3):  # kerbs, ramps and cells mixing two surfaces are outliers of one plane
        coef = np.linalg.lstsq(design[keep], dz[keep], rcond=None)[0]
        residual = np.abs(dz - design @ coef)
        keep = residual <= max(3.0 * np.median(residual[keep]), 0.2)
        if keep.sum() < min_cells:
            return None
    a, b, c = coef
    # a small rotation w about the centre raises a point at (x, y) by w_x * y - w_y * x
    rot = Rotation.from_rotvec([c, -b, 0.0]).as_matrix()
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = centre - rot @ centre + [0.0, 0.0, a]
    return out
