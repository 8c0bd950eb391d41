"""A frame's axis tables (occvo_core/grid_kernels.py): recorded coordinates back bit for bit, and every frame they
cannot describe refused; the repeated-voxel count of the admission check."""

from __future__ import annotations

import numpy as np
import pytest

from occvo_core.grid import OCC3D_GRID
from occvo_schemas.models import Array, SparseOccupancy


def _points(n: int = 4000, seed: int = 3) -> np.ndarray:
    """Voxel centres off by rounding, one coordinate an index, as recorded frames hold them."""
    rng = np.random.default_rng(seed)
    idx = np.stack([rng.integers(0, s, n) for s in OCC3D_GRID.shape], axis=1)
    table = OCC3D_GRID.centre_table() + rng.integers(-2, 3, (3, max(OCC3D_GRID.shape))) * 1e-15
    return OCC3D_GRID.points_of(idx, table)


def test_recorded_coordinates_come_back_bit_for_bit(scene_0101, scene):
    for points in (_points(), scene_0101[0].points, scene[0].points, np.zeros((0, 3))):
        idx, table = OCC3D_GRID.axis_tables(points)
        assert np.array_equal(idx, OCC3D_GRID.indices_of(points))
        assert OCC3D_GRID.points_of(idx.astype(np.uint8), table).tobytes() == np.asarray(points, float).tobytes()


@pytest.mark.parametrize("bad", ["nan", "inf", "below", "above", "two coordinates"])
def test_a_frame_the_tables_cannot_describe_gets_none(bad):
    points = _points()
    if bad == "two coordinates":  # a second coordinate for an index already in use
        points = np.vstack([points, points[:1] + [1e-9, 0.0, 0.0]])
    else:
        points[17, 1] = {"nan": np.nan, "inf": np.inf, "below": -40.01, "above": 40.0}[bad]
    assert OCC3D_GRID.axis_tables(points) is None


def test_repeated_voxels_are_counted_and_refused():
    idx = np.array([[1, 2, 3], [1, 2, 3], [199, 199, 15], [1, 2, 4], [1, 2, 3]], np.uint8)
    labels = Array.from_numpy(np.zeros(len(idx), np.uint8))
    with pytest.raises(ValueError, match="2 duplicate voxels"):
        SparseOccupancy(voxels=Array.from_numpy(idx), labels=labels)
    assert len(SparseOccupancy(voxels=Array.from_numpy(idx[2:4]), labels=Array.from_numpy(np.zeros(2, np.uint8))))
    # in grid order (as replays and the network send them): a repeat is next to its twin, and still refused
    three = Array.from_numpy(np.zeros(3, np.uint8))
    with pytest.raises(ValueError, match="1 duplicate voxels"):
        SparseOccupancy(voxels=Array.from_numpy(idx[[0, 1, 3]]), labels=three)
    assert len(SparseOccupancy(voxels=Array.from_numpy(idx[[0, 3, 2]]), labels=three)) == 3
