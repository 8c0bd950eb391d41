"""First-motion guess without ground truth: correlate bird's-eye views of the static vertical structure.

Geometry-only ICP slides along roads when the car starts fast (scene-0268 moves 4.8 m in the first frame);
buildings, vegetation, poles and barriers seen from above pin down x, y and yaw in one FFT per yaw."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter

STRUCTURE_CLASSES = np.array([1, 8, 15, 16])  # barrier, traffic cone, manmade, vegetation


def _bev(points: np.ndarray, labels: np.ndarray, res: float, size: int) -> np.ndarray:
    keep = np.isin(labels, STRUCTURE_CLASSES)
    ij = np.floor(points[keep, :2] / res).astype(np.int64) + size // 2
    inside = np.all((ij >= 0) & (ij < size), axis=1)
    img = np.zeros((size, size))
    np.add.at(img, (ij[inside, 0], ij[inside, 1]), 1.0)
    img = np.minimum(img, 4.0)  # a tall wall should not outweigh the rest of the scene
    return gaussian_filter(img, 1.0)


def bev_first_motion(prev_points: np.ndarray, prev_labels: np.ndarray, points: np.ndarray, labels: np.ndarray, *,
                     search_radius_m: float, yaw_steps_deg: tuple[float, ...], res: float = 0.8) -> tuple[np.ndarray, float]:
    """Relative motion (4x4, current ego -> previous ego) maximising BEV overlap, and its normalised score."""
    size = int(2 ** np.ceil(np.log2(2 * 60.0 / res)))
    ref_img = _bev(prev_points, prev_labels, res, size)
    ref, ref_norm = np.fft.rfft2(ref_img), np.sqrt((ref_img ** 2).sum())
    limit = int(search_radius_m / res)
    best = (-np.inf, 0.0, 0, 0)
    for yaw_deg in yaw_steps_deg:
        yaw = np.deg2rad(yaw_deg)
        c, s = np.cos(yaw), np.sin(yaw)
        rotated = points[:, :2] @ np.array([[c, s], [-s, c]])
        img = _bev(rotated, labels, res, size)
        corr = np.fft.irfft2(ref * np.conj(np.fft.rfft2(img)), s=(size, size))
        corr = np.roll(corr, (limit, limit), axis=(0, 1))[: 2 * limit + 1, : 2 * limit + 1]
        i, j = np.unravel_index(np.argmax(corr), corr.shape)
        score = corr[i, j] / max(ref_norm * np.sqrt((img ** 2).sum()), 1e-12)
        if score > best[0]:
            best = (score, yaw, i - limit, j - limit)
    score, yaw, di, dj = best
    motion = np.eye(4)
    c, s = np.cos(yaw), np.sin(yaw)
    motion[:2, :2] = [[c, -s], [s, c]]
    motion[:2, 3] = (di * res, dj * res)
    return motion, float(score)
