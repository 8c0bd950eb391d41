"""One occupancy frame: occupied voxel centres in the ego frame with their semantic labels."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from occvo_core.errors import InvalidFrameError
from occvo_core.grid import NUM_CLASSES


@dataclass
class OccupancyFrame:
    points: np.ndarray  # (N,3) float64, metres, ego frame
    labels: np.ndarray  # (N,) uint8, Occ3D class 0..17
    index: int = 0  # frame number in its scene
    stamp: float = 0.0  # seconds
    meta: dict = field(default_factory=dict)

    @classmethod
    def from_array(cls, array: np.ndarray, index: int = 0, stamp: float = 0.0) -> OccupancyFrame:
        """From the OCC-VO release layout: float (N,4) x, y, z, label."""
        array = np.asarray(array)
        if array.ndim != 2 or array.shape[1] != 4:
            raise InvalidFrameError(index, f"expected an (N, 4) array of x, y, z, label, got shape {array.shape}")
        labels = array[:, 3]
        if not np.all(np.isfinite(labels)) or np.any(labels != np.round(labels)):
            raise InvalidFrameError(index, "labels must be whole numbers")
        frame = cls(np.ascontiguousarray(array[:, :3], dtype=np.float64), np.zeros(len(array), np.uint8), index, stamp)
        frame._check_label_range(labels)
        frame.labels = labels.astype(np.uint8)
        return frame

    def _check_label_range(self, labels: np.ndarray) -> None:
        if labels.size and (labels.min() < 0 or labels.max() >= NUM_CLASSES):
            raise InvalidFrameError(
                self.index, f"labels outside 0..{NUM_CLASSES - 1}: min {labels.min()}, max {labels.max()}"
            )

    def validate(self) -> OccupancyFrame:
        """Raise InvalidFrameError naming this frame and the problem; return self when sound."""
        p, l = np.asarray(self.points), np.asarray(self.labels)
        if p.ndim != 2 or p.shape[1] != 3:
            raise InvalidFrameError(self.index, f"points must have shape (N, 3), got {p.shape}")
        if l.ndim != 1 or len(l) != len(p):
            raise InvalidFrameError(self.index, f"labels must have shape ({len(p)},), got {l.shape}")
        if len(p) == 0:
            raise InvalidFrameError(self.index, "frame is empty (no occupied voxels)")
        if not np.issubdtype(p.dtype, np.number) or not np.all(np.isfinite(p)):
            raise InvalidFrameError(
                self.index, f"{int(np.sum(~np.isfinite(p.astype(float))))} non-finite coordinates (NaN or inf)"
            )
        if not np.issubdtype(l.dtype, np.integer):
            raise InvalidFrameError(self.index, f"labels must be integers, got dtype {l.dtype}")
        self._check_label_range(l)
        return self

    def __len__(self) -> int:
        return len(self.points)
