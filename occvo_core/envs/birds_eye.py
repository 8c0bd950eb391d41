"""The bird's-eye image of an episode (render_mode="rgb_array"): the frames placed by the caller's estimates, one
cell of 0.4 m a pixel or coarser, coloured by class (the highest voxel of a cell shows), with the estimated path in
orange and the ground truth's in black where known."""

from __future__ import annotations

import numpy as np

from occvo_core.grid import CLASS_COLORS, OCC3D_GRID

BACKGROUND = (255, 255, 255)
EST_COLOUR, GT_COLOUR = (255, 80, 0), (0, 0, 0)


class BirdsEye:
    def __init__(self, size: int = 512, cell_m: float = OCC3D_GRID.voxel_size):
        self.size, self.cell_m = int(size), float(cell_m)
        self.keys = np.zeros((0, 2), np.int64)  # one row a cell: (ix, iy), its top z, that voxel's class
        self.top = np.zeros(0)
        self.labels = np.zeros(0, np.int64)
        self.est: list[np.ndarray] = []
        self.gt: list[np.ndarray] = []

    def reset(self) -> None:
        self.keys, self.top, self.labels = self.keys[:0], self.top[:0], self.labels[:0]
        self.est.clear()
        self.gt.clear()

    def add(self, points: np.ndarray, labels: np.ndarray, pose: np.ndarray, gt_pose: np.ndarray | None) -> None:
        """A frame's ego-frame points at `pose` (the estimate, in the ground truth's world when aligned)."""
        world = np.asarray(points) @ pose[:3, :3].T + pose[:3, 3]
        keys = np.concatenate([self.keys, np.floor(world[:, :2] / self.cell_m).astype(np.int64)])
        top = np.concatenate([self.top, world[:, 2]])
        labels = np.concatenate([self.labels, np.asarray(labels, np.int64)])
        order = np.lexsort((top, keys[:, 1], keys[:, 0]))  # by cell, then height: a cell's highest voxel last
        keys, top, labels = keys[order], top[order], labels[order]
        last = np.ones(len(keys), bool)
        last[:-1] = np.any(keys[1:] != keys[:-1], axis=1)
        self.keys, self.top, self.labels = keys[last], top[last], labels[last]
        self.est.append(pose[:3, 3].copy())
        if gt_pose is not None:
            self.gt.append(np.asarray(gt_pose)[:3, 3].copy())

    def image(self) -> np.ndarray:
        img = np.full((self.size, self.size, 3), BACKGROUND, np.uint8)
        if not len(self.keys):
            return img
        lo = self.keys.min(axis=0)
        nx, ny = self.keys.max(axis=0) - lo + 1
        cells = np.full((ny, nx, 3), BACKGROUND, np.uint8)  # row 0 is north (+y up)
        cells[ny - 1 - (self.keys[:, 1] - lo[1]), self.keys[:, 0] - lo[0]] = CLASS_COLORS[self.labels]
        scale = (self.size - 8) / max(nx, ny)  # pixels a cell, 4 px of margin
        inner = np.arange(self.size - 8)
        rows = np.minimum((inner / scale).astype(np.int64), ny - 1)
        cols = np.minimum((inner / scale).astype(np.int64), nx - 1)
        h, w = min(self.size - 8, int(np.ceil(ny * scale))), min(self.size - 8, int(np.ceil(nx * scale)))
        img[4 : 4 + h, 4 : 4 + w] = cells[rows[:h]][:, cols[:w]]
        for path, colour in ((self.gt, GT_COLOUR), (self.est, EST_COLOUR)):
            if path:
                p = np.array(path)[:, :2] / self.cell_m - lo
                r = np.clip((ny - p[:, 1]) * scale + 4, 0, self.size - 1).astype(np.int64)
                c = np.clip(p[:, 0] * scale + 4, 0, self.size - 1).astype(np.int64)
                for dr in (-1, 0, 1):
                    for dc in (-1, 0, 1):
                        img[np.clip(r + dr, 0, self.size - 1), np.clip(c + dc, 0, self.size - 1)] = colour
        return img
