"""Occ3D-style labels from LiDAR: box points take the box's class and move with it, the LiDAR mask is the rays'
voxels, nothing behind a wall is in the camera mask, and `occvo make-occupancy` on the shared drive writes what
open_scene reads."""

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from occvo_core.cameras import nuscenes_rig
from occvo_core.datasets.nuscenes_drive import Boxes
from occvo_core.grid import FREE, OCC3D_GRID
from occvo_core.lidar.aggregate import SweepPoints, keyframe_points
from occvo_core.lidar.boxes import points_in_boxes
from occvo_core.lidar.raycast import camera_mask, lidar_mask
from occvo_core.lidar.sweep import DRIVEABLE_SURFACE, label_points

DRIVE = Path(__file__).resolve().parents[3] / "shared" / "data" / "nuscenes-mini"
CAR, PEDESTRIAN = 4, 7


def _yaw(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])


def _boxes(centres, yaws, labels, instances):
    n = len(centres)
    sizes = np.tile([2.0, 4.5, 1.6], (n, 1))  # w, l, h
    return Boxes(np.array(centres, float), np.array([_yaw(y) for y in yaws]), sizes, np.array(labels, np.uint8),
                 list(instances), ["vehicle.car"] * n)  # fmt: skip


def _pose(x, y, yaw):
    p = np.eye(4)
    p[:3, :3], p[:3, 3] = _yaw(yaw), (x, y, 0)
    return p


def test_points_in_a_synthetic_box_get_its_class_and_the_ground_beside_it_does_not():
    rng = np.random.default_rng(0)
    boxes = _boxes([[10.0, 5.0, 0.8]], [30.0], [CAR], ["car-a"])
    inside = rng.uniform([-2.2, -0.9, -0.7], [2.2, 0.9, 0.7], (200, 3)) @ _yaw(30).T + boxes.centres[0]
    ground = np.column_stack([rng.uniform(-30, 30, (2000, 2)), rng.normal(0, 0.03, 2000)])
    ground = ground[points_in_boxes(ground, boxes) < 0]
    labels, box = label_points(np.vstack([inside, ground]), boxes)
    assert np.all(labels[:200] == CAR) and np.all(box[:200] == 0)
    assert np.all(labels[200:] == DRIVEABLE_SURFACE) and np.all(box[200:] == -1)


def test_a_boxs_points_are_carried_to_where_its_instance_is_at_the_keyframe_and_dropped_where_it_has_none():
    # sweep 0: points 1 m in front of the car's centre in its box frame; at keyframe 1 the car is 20 m on and
    # turned; a pedestrian seen at sweep 0 has no box at keyframe 1
    drive_boxes = {
        0: _boxes([[5, 0, 0.8], [0, 8, 0.8]], [0, 0], [CAR, PEDESTRIAN], ["car-a", "ped-b"]),
        1: _boxes([[25, 3, 0.8]], [90], [CAR], ["car-a"]),
    }
    frames = [SimpleNamespace(ego_pose=_pose(0, 0, 0)), SimpleNamespace(ego_pose=_pose(10, 0, 0))]
    drive = type("Drive", (), {"__getitem__": lambda self, i: frames[i], "boxes": lambda self, i: drive_boxes[i]})()
    static = np.array([[30.0, -5.0, 1.0]])
    sweep = SweepPoints(np.zeros(3), static, np.array([15], np.uint8),
                        {"car-a": np.array([[1.0, 0.0, 0.0]]), "ped-b": np.array([[0.0, 0.0, 0.0]])})  # fmt: skip
    agg = keyframe_points(drive, {0: sweep}, 1)
    # keyframe 1's ego sits at x = 10: the static point at 20, -5; the car's point 1 m along its heading (+y now)
    np.testing.assert_allclose(agg.points, [[20.0, -5.0, 1.0], [15.0, 4.0, 0.8]], atol=1e-12)
    assert agg.labels.tolist() == [15, CAR]
    np.testing.assert_allclose(agg.origin[0], [-10.0, 0.0, 0.0])
    assert np.all(np.isnan(agg.origin[1]))  # another sweep's box point casts no ray at this keyframe


def test_the_lidar_mask_holds_the_voxels_a_ray_crosses_and_its_end_and_nothing_beyond():
    origin = np.array([[0.2, 0.2, 1.8]])
    end = np.array([[10.2, 0.2, 1.8]])
    observed = lidar_mask(end, origin)
    i0, j, k = OCC3D_GRID.indices_of(origin)[0]
    i1 = OCC3D_GRID.indices_of(end)[0][0]
    line = observed[:, j, k]
    assert line[i0 : i1 + 1].all() and not line[:i0].any() and not line[i1 + 1 :].any()
    assert observed.sum() == i1 - i0 + 1
    # a ray from far outside the grid marks its part inside; a NaN origin marks the end voxel only
    assert lidar_mask(end, np.array([[-100.2, 0.2, 1.8]]))[:, j, k].sum() == i1 + 1
    assert lidar_mask(end, np.full((1, 3), np.nan)).sum() == 1


def test_a_voxel_behind_a_wall_around_the_car_is_outside_the_camera_mask_and_one_before_it_inside():
    sem = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    column = OCC3D_GRID.lower[0] + (np.arange(OCC3D_GRID.shape[0]) + 0.5) * OCC3D_GRID.voxel_size
    reach = np.maximum(np.abs(column)[:, None], np.abs(column)[None, :])  # square rings around the car
    sem[(reach > 12.0) & (reach < 12.4)] = 15  # a wall 12 m out, the grid's full height
    visible = camera_mask(sem, nuscenes_rig())
    behind = (reach > 13.0)[..., None] & np.ones(OCC3D_GRID.shape, bool)
    assert not visible[behind].any()
    assert visible[tuple(OCC3D_GRID.indices_of([[6.0, 0.2, 1.0]])[0])]  # in front of the wall, before CAM_FRONT
    assert visible[(reach > 12.0) & (reach < 12.4)].mean() > 0.5  # the wall itself is seen


@pytest.fixture(scope="module")
def drive():
    if not (DRIVE / "v1.0-mini" / "scene.json").is_file():
        pytest.skip(f"the real nuScenes drive is not at {DRIVE} (it sits beside the checkout in CI)")
    from occvo_core.datasets.nuscenes_drive import NuScenesDrive

    return NuScenesDrive(DRIVE, "scene-0916")


def test_on_the_real_drive_the_points_of_each_box_get_its_class_also_when_carried_from_other_sweeps(drive):
    from occvo_core.lidar.aggregate import sweep_points
    from occvo_core.lidar.boxes import boxes_in_frame

    sweeps = {j: sweep_points(drive, j) for j in (0, 2, 4)}
    agg = keyframe_points(drive, sweeps, 2)
    boxes = boxes_in_frame(drive.boxes(2), np.linalg.inv(drive[2].ego_pose))
    boxed = ~np.isin(agg.labels, (DRIVEABLE_SURFACE, 15))
    assert boxed.sum() > 1000  # cars, a bus, pedestrians: thousands of points
    box = points_in_boxes(agg.points[boxed], boxes)
    assert np.mean(box >= 0) == 1.0  # every carried point lands in a box at keyframe 2 (within the 10 cm margin)
    assert np.mean(boxes.labels[box] == agg.labels[boxed]) > 0.99  # its own class (boxes may touch)
    assert {CAR, PEDESTRIAN} <= set(np.unique(agg.labels[boxed]).tolist())


def test_make_occupancy_on_the_shared_drive_writes_41_frames_that_open_scene_reads(drive, tmp_path, capsys):
    from occvo_cli.cli import main
    from occvo_core.datasets import open_scene

    out = tmp_path / "occ3d"
    assert main(["make-occupancy", "--input", str(DRIVE), "--sweeps-from", "10-12", "--out", str(out), "--quiet"]) == 0
    assert "41 keyframes written" in capsys.readouterr().out
    scene = open_scene(out, scene="scene-0916")
    assert len(scene) == 41 and np.all(np.diff(scene.stamps) > 0)
    np.testing.assert_allclose(scene.gt_poses, drive.gt_poses, atol=1e-9)
    np.testing.assert_allclose(scene.stamps, drive.stamps)
    with np.load(out / "gts" / "scene-0916" / drive[11].token / "labels.npz") as z:
        assert {k: (z[k].shape, z[k].dtype.name) for k in z.files} == {
            k: ((200, 200, 16), "uint8") for k in ("semantics", "mask_lidar", "mask_camera")
        }
        sem, lidar, cam = z["semantics"], z["mask_lidar"].astype(bool), z["mask_camera"].astype(bool)
    assert lidar[sem != FREE].all()  # every occupied voxel holds a point: the LiDAR saw it
    assert 0.05 < cam.mean() < lidar.mean() < 0.95
    assert {CAR, DRIVEABLE_SURFACE, 15} <= set(np.unique(sem).tolist())
    assert open_scene(out / "gts" / "scene-0916", mask="lidar")[11].points.shape[0] == (sem != FREE).sum()


def test_make_occupancy_says_in_one_line_when_a_range_is_past_the_drive(drive, tmp_path, capsys):
    from occvo_cli.cli import main

    assert main(["make-occupancy", "--input", str(DRIVE), "--keyframes", "40-41", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["occvo make-occupancy: error: --keyframes 40-41: the scene has keyframes 0-40"]


def test_make_occupancy_refuses_an_annotations_json_that_is_not_occ3ds_before_making_labels(drive, tmp_path, capsys):
    from occvo_cli.cli import main

    (tmp_path / "annotations.json").write_text('{"not": "occ3d"}')
    assert main(["make-occupancy", "--input", str(DRIVE), "--out", str(tmp_path), "--quiet"]) == 2
    assert "scene_infos" in capsys.readouterr().err
    assert not (tmp_path / "gts").exists()


def test_labels_written_into_an_occ3d_root_keep_its_other_scenes_and_splits(drive, tmp_path):
    import json

    from occvo_cli.cli import main
    from occvo_core.datasets.occ3d_nuscenes import list_scenes

    other = {"scene-0001": {"t0": {"timestamp": 1, "prev": "EOF", "next": "EOF"}}}
    (tmp_path / "annotations.json").write_text(json.dumps({"train_split": ["scene-0001"], "scene_infos": other}))
    args = ["make-occupancy", "--input", str(DRIVE), "--keyframes", "6-7", "--sweeps-from", "6-7", "--quiet"]
    assert main([*args, "--out", str(tmp_path)]) == 0
    written = json.loads((tmp_path / "annotations.json").read_text())
    assert written["train_split"] == ["scene-0001"] and written["scene_infos"]["scene-0001"] == other["scene-0001"]
    assert [(s["scene"], s["samples"]) for s in list_scenes(tmp_path)] == [("scene-0001", 1), ("scene-0916", 2)]
