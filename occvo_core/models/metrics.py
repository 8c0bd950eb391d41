"""Occ3D-style occupancy metrics: mIoU over the 17 semantic classes and geometry IoU, inside the camera mask."""

from __future__ import annotations

import numpy as np

from occvo_core.grid import CLASS_NAMES, FREE, NUM_CLASSES


class OccMetrics:
    """Accumulates one confusion matrix (rows = truth, columns = prediction) over every evaluated voxel.

    As in the Occ3D benchmark, IoU is computed from the totals over the whole set; a class with no truth and no
    prediction is NaN and left out of the mean; a class predicted but never true scores 0.
    """

    def __init__(self, num_classes: int = NUM_CLASSES):
        self.num_classes = num_classes
        self.hist = np.zeros((num_classes, num_classes), np.int64)
        self.frames = 0

    def update(self, pred: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None) -> None:
        pred, truth = np.asarray(pred).astype(np.int64), np.asarray(truth).astype(np.int64)
        if pred.shape != truth.shape:
            raise ValueError(f"prediction shape {pred.shape} != truth shape {truth.shape}")
        if mask is not None:
            mask = np.asarray(mask, bool)
            if mask.shape != truth.shape:
                raise ValueError(f"mask shape {mask.shape} != truth shape {truth.shape}")
            pred, truth = pred[mask], truth[mask]
        k = self.num_classes
        self.hist += np.bincount(truth.ravel() * k + pred.ravel(), minlength=k * k).reshape(k, k)
        self.frames += 1

    def per_class_iou(self) -> np.ndarray:
        """IoU of the semantic classes 0..16 (NaN where a class is neither true nor predicted)."""
        tp = np.diag(self.hist).astype(np.float64)
        denom = self.hist.sum(0) + self.hist.sum(1) - tp
        with np.errstate(divide="ignore", invalid="ignore"):
            iou = tp / denom
        return iou[:FREE]

    def miou(self) -> float:
        iou = self.per_class_iou()
        return float(np.nanmean(iou)) if np.any(np.isfinite(iou)) else float("nan")

    def geometry_iou(self) -> float:
        """Occupied (any class but free) against free."""
        tp = self.hist[:FREE, :FREE].sum()
        fp = self.hist[FREE, :FREE].sum()
        fn = self.hist[:FREE, FREE].sum()
        return float(tp / (tp + fp + fn)) if tp + fp + fn else float("nan")

    def summary(self) -> dict:
        iou = self.per_class_iou()
        return {
            "frames": self.frames,
            "voxels": int(self.hist.sum()),
            "miou": self.miou(),
            "geometry_iou": self.geometry_iou(),
            "per_class_iou": {CLASS_NAMES[c]: (None if np.isnan(v) else float(v)) for c, v in enumerate(iou)},
        }
