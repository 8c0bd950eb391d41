"""Heavy frames: a scene's frames with ten times their occupied voxels, for a stream whose registration costs
several times a normal one's (benchmarks/noisy_neighbour.py, tests/service/test_neighbours.py).

    heavy = HeavyScene(SyntheticScene(seed=2, frames=12), factor=10)
    heavy[0]   # scene[0] with its voxels' neighbouring cells occupied too: 10x the voxels, same labels

A frame's voxels are grown into the cells next to them (nearest offsets first, the labels copied), each cell once,
until the frame holds `factor` times its voxels: the same scene, thicker, so registration still converges."""

from __future__ import annotations

import numpy as np

from occvo_core.frame import OccupancyFrame
from occvo_core.grid import OCC3D_GRID, GridSpec

# cell offsets by distance: a frame grows into its nearest neighbouring cells first
_OFFSETS = sorted(
    ((dx, dy, dz) for dx in range(-3, 4) for dy in range(-3, 4) for dz in range(-3, 4)),
    key=lambda o: (o[0] ** 2 + o[1] ** 2 + o[2] ** 2, o),
)


def thicken(frame: OccupancyFrame, factor: int = 10, grid: GridSpec = OCC3D_GRID) -> OccupancyFrame:
    """frame with its voxels grown into neighbouring cells until it holds factor x its voxels (fewer only when the
    offsets up to 3 cells away run out)."""
    idx, shape = grid.indices_of(frame.points), np.array(grid.shape)
    want = factor * len(idx)
    taken = np.zeros(int(np.prod(shape)), np.bool_)
    cells, labels = [], []
    for offset in _OFFSETS:
        v = idx + np.array(offset)
        v, lab = v[grid.inside(v)], frame.labels[grid.inside(v)]
        lin = (v[:, 0] * shape[1] + v[:, 1]) * shape[2] + v[:, 2]
        _, first = np.unique(lin, return_index=True)
        new = np.sort(first[~taken[lin[first]]])[: want - sum(len(c) for c in cells)]
        taken[lin[new]] = True
        cells.append(v[new]), labels.append(lab[new])
        if sum(len(c) for c in cells) >= want:
            break
    return OccupancyFrame(grid.centres_of(np.concatenate(cells)), np.concatenate(labels), frame.index, frame.stamp)


class HeavyScene:
    """scene's frames, each thickened (thicken); the rest of the scene (poses, rate) is scene's."""

    def __init__(self, scene, factor: int = 10):
        self.scene, self.factor = scene, factor

    def __len__(self) -> int:
        return len(self.scene)

    def __getitem__(self, i: int) -> OccupancyFrame:
        return thicken(self.scene[i], self.factor)
