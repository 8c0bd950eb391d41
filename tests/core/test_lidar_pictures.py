"""The pictures of make-occupancy --pictures: the view from above keeps the ego's axes (x up, y left), and on the
shared drive the LiDAR points of the cars land on the cameras' images in the car colour."""

from pathlib import Path

import numpy as np
import pytest

from occvo_core.grid import CLASS_COLORS, FREE, OCC3D_GRID
from occvo_core.viz.lidar_pictures import top_view

DRIVE = Path(__file__).resolve().parents[3] / "shared" / "data" / "nuscenes-mini"
CAR, MANMADE = 4, 15


def test_from_above_ahead_is_up_left_is_left_and_a_column_shows_its_highest_voxel():
    sem = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    ahead, left = OCC3D_GRID.indices_of([[30.0, 0.1, 0.0], [0.1, 30.0, 0.0]])
    sem[tuple(ahead)] = CAR
    sem[left[0], left[1], 2:6] = (11, 11, MANMADE, MANMADE)
    image = top_view(sem)
    rows, cols = np.nonzero(np.any(image != 30, axis=2))
    assert sorted(zip(rows.tolist(), cols.tolist())) == [(24, 99), (99, 24)]
    assert image[24, 99].tolist() == CLASS_COLORS[CAR].tolist()  # 30 m ahead: a quarter of the way down
    assert image[99, 24].tolist() == CLASS_COLORS[MANMADE].tolist()  # 30 m left, the wall above the ground
    masked = top_view(sem, np.zeros(OCC3D_GRID.shape, bool))
    assert np.all(masked == 30)


def test_make_occupancy_pictures_put_the_cars_points_on_the_cars(tmp_path):
    if not (DRIVE / "v1.0-mini" / "scene.json").is_file():
        pytest.skip(f"the real nuScenes drive is not at {DRIVE} (it sits beside the checkout in CI)")
    from PIL import Image

    from occvo_cli.cli import main

    args = ["make-occupancy", "--input", str(DRIVE), "--keyframes", "20-20", "--sweeps-from", "20-20", "--quiet"]
    assert main([*args, "--out", str(tmp_path / "occ"), "--pictures", str(tmp_path / "pics")]) == 0
    written = sorted(p.name for p in (tmp_path / "pics" / "scene-0916").iterdir())
    assert len(written) == 7 and "020_CAM_FRONT.png" in written and "020_above.png" in written
    front = np.asarray(Image.open(tmp_path / "pics" / "scene-0916" / "020_CAM_FRONT.png"))
    assert front.shape == (450, 800, 3)
    car_pixels = np.all(front == CLASS_COLORS[CAR], axis=2)
    assert car_pixels.sum() > 500  # parked cars on both sides of the lane
    # the car points lie below the horizon row: cars stand on the ground, not in the trees
    assert np.median(np.nonzero(car_pixels)[0]) > 450 * 0.5
