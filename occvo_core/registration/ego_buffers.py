"""Arrays that the EgoMap of each frame reuses: a frame's ego grid, positions and covariances are megabytes, and
fresh megabytes every frame cost more in page faults than moving the voxels does."""

from __future__ import annotations

import numpy as np

from occvo_core.registration.kernels.map_window import clear_cells, empty_grid


class EgoBuffers:
    """Owns the arrays; take() hands them out for one EgoMap, and the EgoMap taken before is invalid from then on
    (its grid is emptied where it was written, not wholly: the box is the same every frame)."""

    def __init__(self) -> None:
        self._grid = np.zeros(0, np.int32)
        self._cells = np.zeros(0, np.int64)
        self._written = 0  # cells[:written] hold the last EgoMap's cells
        self._pos = np.zeros((0, 3))
        self._cov = np.zeros((0, 3, 3))

    def take(self, n: int, n_cells: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(pos, cov, grid with every cell empty, cell_of) for an EgoMap of n points on a grid of n_cells."""
        if len(self._grid) != n_cells:
            self._grid = empty_grid(n_cells)
        else:
            clear_cells(self._grid, self._cells[: self._written])
        if len(self._pos) < n:
            size = n + n // 4  # room to grow: the window's voxels vary a little frame to frame
            self._pos, self._cov, self._cells = np.empty((size, 3)), np.empty((size, 3, 3)), np.empty(size, np.int64)
        self._written = n
        return self._pos[:n], self._cov[:n], self._grid, self._cells[:n]
