"""The semantic BEV motion search that refines each frame's constant-velocity guess (a turn starting between frames)."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from occvo_core.registration.initialisation import semantic_bev_motion
from occvo_core.sim import SyntheticScene


def _motion(yaw_deg: float, x: float, y: float) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("z", yaw_deg, degrees=True).as_matrix()
    m[:2, 3] = (x, y)
    return m


@pytest.mark.parametrize("yaw_deg, x, y", [(11.0, 2.0, 0.4), (-7.0, 3.2, -0.8), (0.0, 1.6, 0.0)])
def test_the_search_finds_a_turn_the_constant_velocity_guess_lacks(yaw_deg, x, y):
    frame = SyntheticScene(seed=3, frames=2)[0]
    true = _motion(yaw_deg, x, y)  # current ego -> previous ego
    current = frame.points @ np.linalg.inv(true)[:3, :3].T + np.linalg.inv(true)[:3, 3]
    guess = _motion(0.0, x + 0.8, y - 0.4)  # no turn, and the translation off by 0.9 m
    found = semantic_bev_motion(
        frame.points,
        frame.labels,
        current,
        frame.labels,
        guess=guess,
        search_radius_m=4.0,
        yaw_deg=16.0,
        step_deg=2.0,
        prior_sigma_m=1.0,
    )
    yaw = np.rad2deg(Rotation.from_matrix(found[:3, :3]).as_euler("zyx")[0])
    assert abs(yaw - yaw_deg) <= 1.0 + 1e-9, yaw
    # the x-y move is held near the guess by its prior (a straight road does not fix it): left to coarse GICP, whose
    # wide pass reaches 2.4 m
    assert np.linalg.norm(found[:2, 3] - true[:2, 3]) < 1.2, found[:2, 3]
    assert np.array_equal(found[2], guess[2])  # height is left to GICP


@pytest.mark.parametrize(
    "from_images, flag, expected", [(True, None, True), (False, None, False), (True, False, False), (False, True, True)]
)
def test_occvo_run_searches_on_camera_occupancy_unless_told(from_images, flag, expected):
    from argparse import Namespace

    from occvo_cli.commands.run import config_from_args

    args = Namespace(
        config=None,
        from_images=from_images,
        motion_search=flag,
        no_semantic_filter=False,
        no_dynamic_filter=False,
        no_pfilter=False,
    )
    assert config_from_args(args).initialisation.motion_search is expected
