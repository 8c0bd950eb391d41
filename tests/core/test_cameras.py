"""The nuScenes rig projects known points into the right pixels of the right camera; the renderer sees what is there."""

import numpy as np
import pytest

from occvo_core.cameras import CAMERA_NAMES, nuscenes_rig, render
from occvo_core.grid import FREE, OCC3D_GRID

FRONT, FRONT_LEFT, FRONT_RIGHT, BACK = (
    CAMERA_NAMES.index(n) for n in ("CAM_FRONT", "CAM_FRONT_LEFT", "CAM_FRONT_RIGHT", "CAM_BACK")
)


def test_rig_layout_matches_nuscenes():
    rig = nuscenes_rig()
    assert rig.size == (1600, 900) and rig.intrinsics.shape == (6, 3, 3) and rig.cam_to_ego.shape == (6, 4, 4)
    assert rig.intrinsics[FRONT, 0, 0] == pytest.approx(1266.4, abs=1)
    assert rig.intrinsics[BACK, 0, 0] < 0.7 * rig.intrinsics[FRONT, 0, 0]  # the wider back camera
    yaws = np.degrees(np.arctan2(rig.cam_to_ego[:, 1, 2], rig.cam_to_ego[:, 0, 2]))  # optical axis in the ego frame
    np.testing.assert_allclose(yaws, [0, 55, -55, 180, 110, -110], atol=1e-6)
    assert np.all((rig.cam_to_ego[:, 2, 3] > 1.4) & (rig.cam_to_ego[:, 2, 3] < 1.7))
    np.testing.assert_allclose(np.linalg.det(rig.cam_to_ego[:, :3, :3]), 1.0)


def test_known_points_land_on_the_right_pixels_of_the_right_cameras():
    rig = nuscenes_rig()
    k, t = rig.intrinsics, rig.cam_to_ego[:, :3, 3]
    ahead = t[FRONT] + [20.0, 0, 0]  # on the front optical axis -> principal point
    left = t[FRONT] + [20.0, 2.0, -1.0]  # left and below -> left of and under the centre
    along_fl = t[FRONT_LEFT] + 15 * np.array([np.cos(np.radians(55)), np.sin(np.radians(55)), 0])
    behind = t[BACK] + [-12.0, 0, 0]
    uv, depth, valid = rig.project(np.array([ahead, left, along_fl, behind]))
    np.testing.assert_allclose(uv[FRONT, 0], k[FRONT, :2, 2], atol=1e-6)
    assert depth[FRONT, 0] == pytest.approx(20.0)
    np.testing.assert_allclose(
        uv[FRONT, 1], [k[FRONT, 0, 2] - 1266.4 * 2 / 20, k[FRONT, 1, 2] + 1266.4 * 1 / 20], atol=1e-6
    )
    np.testing.assert_allclose(uv[FRONT_LEFT, 2], k[FRONT_LEFT, :2, 2], atol=1e-6)
    np.testing.assert_allclose(uv[BACK, 3], k[BACK, :2, 2], atol=1e-6)
    assert valid[:, 0].tolist() == [True, False, False, False, False, False]
    assert valid[BACK, 3] and not valid[FRONT, 3] and depth[FRONT, 3] < 0  # behind the front camera: rejected
    assert valid[FRONT_LEFT, 2] and not valid[FRONT_RIGHT, 2]


def test_scaled_rig_keeps_pixel_centres():
    full, small = nuscenes_rig(), nuscenes_rig(200, 112)
    pts = np.array([[20.0, 3.0, 1.0], [-8.0, 5.0, 0.5], [4.0, -9.0, 2.0]])
    uv_full, _, _ = full.project(pts)
    uv_small, _, valid = small.project(pts)
    expect = (uv_full + 0.5) * np.array([200 / 1600, 112 / 900]) - 0.5
    np.testing.assert_allclose(uv_small, expect, atol=1e-9)
    assert valid.any(axis=0).all()  # the surround rig sees every horizontal direction


def _wall_world():
    g = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    g[:, :, 2] = 11  # driveable surface, the voxel layer centred on z = 0
    ix = int((20.0 - OCC3D_GRID.lower[0]) / 0.4)  # wall of manmade from x = 20 m to 20.8 m
    g[ix : ix + 2, 75:125, 3:16] = 15
    return g, ix


def test_renderer_sees_the_wall_ahead_and_the_floor_below():
    g, ix = _wall_world()
    rig = nuscenes_rig(200, 112)
    out = render(g, rig, rng=0)
    assert out.images.shape == (6, 112, 200, 3) and out.images.dtype == np.uint8
    cy, cx = int(round(rig.intrinsics[FRONT, 1, 2])), int(round(rig.intrinsics[FRONT, 0, 2]))
    assert out.labels[FRONT, cy, cx] == 15
    assert out.depth[FRONT, cy, cx] == pytest.approx(20.0 - rig.cam_to_ego[FRONT, 0, 3], abs=0.05)
    assert out.labels[FRONT, -1, cx] == 11 and out.labels[BACK, -1, 100] == 11
    assert out.labels[BACK, 0, 100] == 255  # sky: the ray leaves the grid without a hit
    # Class colour shows through shading, fog and noise: the wall is bluish-white, the road magenta.
    wall, road = (
        out.images[FRONT, cy - 3 : cy + 3, cx - 3 : cx + 3].reshape(-1, 3).mean(0),
        out.images[FRONT, -4:, :].reshape(-1, 3).mean(0),
    )
    assert wall[2] > wall[1] and road[0] > road[1] and road[2] > road[1]
    # Camera mask: the wall's front face is seen, what is behind the wall and under the road is not.
    mask = out.camera_mask
    assert mask[ix, 100, 5] and not mask[ix + 1, 100, 5] and not mask[ix + 5, 100, 5]
    assert mask[ix - 10, 100, 5] and mask[ix - 10, 100, 2] and not mask[ix - 10, 100, 1]


def test_renderer_is_seeded_and_rejects_bad_grids():
    g, _ = _wall_world()
    rig = nuscenes_rig(64, 36)
    np.testing.assert_array_equal(render(g, rig, rng=3).images, render(g, rig, rng=3).images)
    assert not np.array_equal(render(g, rig, rng=3).images, render(g, rig, rng=4).images)
    with pytest.raises(ValueError, match="shape"):
        render(g[:, :, :8], rig)
