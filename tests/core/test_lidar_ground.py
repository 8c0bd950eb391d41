"""The ground rule of a LiDAR sweep: points near the local lowest height are ground, and one stray return under the
road does not sink the ground of the columns around it."""

import numpy as np

from occvo_core.lidar.ground import ground_mask


def _flat_road_with_a_wall(rng):
    road = np.column_stack([rng.uniform(-20, 20, 4000), rng.uniform(-20, 20, 4000), rng.normal(0, 0.02, 4000)])
    wall = np.column_stack([np.full(800, 8.0), rng.uniform(-5, 5, 800), rng.uniform(0.5, 3.0, 800)])
    return road, wall


def test_road_is_ground_and_a_wall_is_not():
    road, wall = _flat_road_with_a_wall(np.random.default_rng(0))
    g = ground_mask(np.vstack([road, wall]))
    assert g[: len(road)].all() and not g[len(road) :].any()


def test_a_stray_return_under_the_road_leaves_the_road_ground():
    road, wall = _flat_road_with_a_wall(np.random.default_rng(1))
    stray = np.array([[6.5, 3.1, -3.2]])  # a multipath return 3 m under the road, as in scene-0916's keyframe 10
    g = ground_mask(np.vstack([road, wall, stray]))
    near = np.abs(road[:, :2] - stray[0, :2]).max(axis=1) < 4.0  # the columns its floor would have sunk
    assert near.sum() > 50 and g[: len(road)][near].all()
