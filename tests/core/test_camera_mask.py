"""The camera mask of a prediction (occvo_core.models.camera_mask): fans from the calibration see what the synthetic
town's own camera mask sees, and a solid block keeps the faces the cameras see, not its inside."""

from __future__ import annotations

import numpy as np

from occvo_core.cameras import nuscenes_rig
from occvo_core.grid import FREE, OCC3D_GRID
from occvo_core.models.camera_mask import camera_fans, masked
from occvo_core.sim import SyntheticScene
from occvo_core.sim.render import visible


def test_fans_from_the_calibration_see_what_the_towns_camera_mask_sees():
    rig = nuscenes_rig(200, 112)
    fans = camera_fans(rig.intrinsics, rig.cam_to_ego, 200, 112)
    scene = SyntheticScene(seed=3, frames=2)
    grid = scene.true_grid(1)
    ours, towns = visible(grid, fans), scene.camera_mask(1)
    occupied = grid != FREE
    seen_by_both = np.count_nonzero(ours & towns & occupied)
    # the town's fans are the same cameras with centred principal points and a lower top: edge voxels differ
    assert seen_by_both >= 0.95 * np.count_nonzero(towns & occupied), (seen_by_both, np.count_nonzero(towns & occupied))
    assert seen_by_both >= 0.95 * np.count_nonzero(ours & occupied)


def test_a_solid_block_keeps_its_seen_faces_only():
    grid = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    grid[125:150, 90:110, :] = 15  # manmade, x 10-20 m ahead, y -4..4 m, floor to ceiling
    rig = nuscenes_rig(200, 112)
    out = masked(grid, OCC3D_GRID, rig.intrinsics, rig.cam_to_ego, (200, 112))
    kept = out != FREE
    assert np.all(out[kept] == 15)
    assert kept[125, 95:105, 2:6].all()  # the face towards the front camera
    assert not kept[127:150, 91:109, :].any()  # its inside and far side
    assert np.count_nonzero(kept) < 0.1 * np.count_nonzero(grid != FREE)
