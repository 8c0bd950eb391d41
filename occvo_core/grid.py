"""The Occ3D-nuScenes occupancy grid: 200x200x16 voxels of 0.4 m, 18 classes (17 = free)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occvo_core.grid_kernels import fill_axis_tables, gather_points

CLASS_NAMES: tuple[str, ...] = (
    "others",
    "barrier",
    "bicycle",
    "bus",
    "car",
    "construction_vehicle",
    "motorcycle",
    "pedestrian",
    "traffic_cone",
    "trailer",
    "truck",
    "driveable_surface",
    "other_flat",
    "sidewalk",
    "terrain",
    "manmade",
    "vegetation",
    "free",
)
NUM_CLASSES = len(CLASS_NAMES)  # 18
FREE = 17
# Classes that may move: the dynamic object filter clusters these (the paper's movable set).
MOVABLE_CLASSES: tuple[int, ...] = (0, 2, 3, 4, 5, 6, 7, 9, 10)
STATIC_CLASSES: tuple[int, ...] = tuple(c for c in range(FREE) if c not in MOVABLE_CLASSES)
GROUND_CLASSES: tuple[int, ...] = (11, 12, 13, 14)  # driveable surface, other flat, sidewalk, terrain

# Occ3D-nuScenes palette (RGB, 0..255), as used by the benchmark's visualiser.
CLASS_COLORS = np.array(
    [
        [0, 0, 0],
        [255, 120, 50],
        [255, 192, 203],
        [255, 255, 0],
        [0, 150, 245],
        [0, 255, 255],
        [200, 180, 0],
        [255, 0, 0],
        [255, 240, 150],
        [135, 60, 0],
        [160, 32, 240],
        [255, 0, 255],
        [139, 137, 137],
        [75, 0, 75],
        [150, 240, 80],
        [230, 230, 250],
        [0, 175, 0],
        [255, 255, 255],
    ],
    dtype=np.uint8,
)


@dataclass(frozen=True)
class GridSpec:
    """Axis-aligned voxel grid in the ego frame; voxel i along an axis has centre lower + (i + 0.5) * voxel."""

    lower: tuple[float, float, float] = (-40.0, -40.0, -1.0)
    upper: tuple[float, float, float] = (40.0, 40.0, 5.4)
    voxel_size: float = 0.4

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(int(round((u - l) / self.voxel_size)) for l, u in zip(self.lower, self.upper))  # type: ignore[return-value]

    def indices_of(self, points: np.ndarray) -> np.ndarray:
        """Integer voxel indices (N,3) of points (N,3); may fall outside the grid."""
        points = np.asarray(points, np.float64)
        return np.stack([self.axis_indices(a, points[:, a]) for a in range(3)], axis=1)

    def axis_indices(self, a: int, coords: np.ndarray) -> np.ndarray:
        """Voxel indices along axis a of coordinates along it (may fall outside the grid); NaN / inf give a negative
        index."""
        with np.errstate(invalid="ignore"):
            return np.floor((np.asarray(coords, np.float64) - self.lower[a]) / self.voxel_size).astype(np.int64)

    def centres_of(self, indices: np.ndarray) -> np.ndarray:
        return np.array(self.lower) + (np.asarray(indices, dtype=np.float64) + 0.5) * self.voxel_size

    def inside(self, indices: np.ndarray) -> np.ndarray:
        return np.all((indices >= 0) & (indices < np.array(self.shape)), axis=1)

    def axis_tables(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Points as voxel indices (N,3) and a table (3, max(shape)) whose row a holds the coordinate of each index
        along axis a (the nominal centre where no point says otherwise), which give the points back bit for bit
        (points_of); None when they do not (a point outside, or an index with two coordinates). Recorded frames hold
        voxel centres only to within rounding: this way they travel and are kept exactly, 3 bytes a voxel."""
        points = np.ascontiguousarray(points, np.float64)
        table, idx = self.centre_table(), np.empty((len(points), 3), np.int64)
        if not fill_axis_tables(points, np.array(self.lower), self.voxel_size, np.array(self.shape), table, idx):
            return None
        return idx, table

    def centre_table(self) -> np.ndarray:
        """(3, max(shape)): row a holds the centre of each index along axis a, as centres_of computes it."""
        return np.array(self.lower)[:, None] + (np.arange(max(self.shape)) + 0.5) * self.voxel_size

    @staticmethod
    def points_of(indices: np.ndarray, table: np.ndarray) -> np.ndarray:
        """The points axis_tables() describes."""
        indices, k = np.asarray(indices), table.shape[1]
        if indices.size and (indices.min() < 0 or indices.max() >= k):
            raise IndexError(f"voxel indices outside 0..{k - 1}")
        return gather_points(indices, np.ascontiguousarray(table, np.float64))


OCC3D_GRID = GridSpec()


def grid_to_points(
    semantics: np.ndarray, grid: GridSpec = OCC3D_GRID, mask: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Occupied voxels (label != free, and mask true where given) of a dense label grid -> (points (N,3), labels (N,))."""
    semantics = np.asarray(semantics)
    if semantics.shape != grid.shape:
        raise ValueError(f"semantics grid has shape {semantics.shape}, expected {grid.shape}")
    occupied = semantics != FREE
    if mask is not None:
        occupied &= np.asarray(mask, dtype=bool)
    idx = np.argwhere(occupied)
    return grid.centres_of(idx), semantics[occupied].astype(np.uint8)


def points_to_grid(points: np.ndarray, labels: np.ndarray, grid: GridSpec = OCC3D_GRID) -> np.ndarray:
    """Labelled points -> dense uint8 label grid (free where empty); points outside the grid are ignored."""
    out = np.full(grid.shape, FREE, dtype=np.uint8)
    idx = grid.indices_of(points)
    keep = grid.inside(idx)
    idx = idx[keep]
    out[idx[:, 0], idx[:, 1], idx[:, 2]] = np.asarray(labels)[keep]
    return out
