"""The nuScenes reader on the shared real drive (scene-0916): keyframes, cameras, stamps, poses, boxes, and the
projection of LiDAR points into each camera by occvo's camera model against nuscenes-devkit's own chain."""

import json

import numpy as np
import pytest
from nuscenes_sample import DRIVE

from occvo_core.cameras import CAMERA_NAMES


def _table(name):
    return {r["token"]: r for r in json.loads((DRIVE / "v1.0-mini" / f"{name}.json").read_text())}


def test_the_reader_gives_41_keyframes_six_cameras_increasing_stamps_and_the_tables_ego_poses(drive):
    from scipy.spatial.transform import Rotation

    assert len(drive) == 41 and drive.name == "scene-0916"
    assert np.all(np.diff(drive.stamps) > 0)
    sample_data, ego_pose = _table("sample_data"), _table("ego_pose")
    lidar = {
        sd["sample_token"]: sd for sd in sample_data.values() if sd["is_key_frame"] and "LIDAR_TOP" in sd["filename"]
    }
    for k in drive.samples:
        assert len(k.files) == 6 and all(f.is_file() for f in k.files)
        assert [f.parent.name for f in k.files] == list(CAMERA_NAMES)
        assert np.all(np.abs(k.camera_stamps - k.stamp) < 0.1) and k.lidar_file.is_file()
        record = ego_pose[lidar[k.token]["ego_pose_token"]]
        w, x, y, z = record["rotation"]
        assert np.allclose(k.ego_pose[:3, 3], record["translation"], atol=0, rtol=0)
        assert np.allclose(k.ego_pose[:3, :3], Rotation.from_quat([x, y, z, w]).as_matrix(), atol=1e-15)
    path = np.linalg.norm(np.diff(drive.gt_poses[:, :3, 3], axis=0), axis=1).sum()
    assert 93 < path < 94  # the drive's 93.4 m
    assert sum(len(drive.boxes(i)) for i in range(len(drive))) == 2424


def test_lidar_points_project_into_every_camera_as_the_devkit_projects_them(drive):
    pytest.importorskip("nuscenes.utils.geometry_utils", reason="nuscenes-devkit is not installed")
    from nuscenes.utils.data_classes import LidarPointCloud
    from nuscenes.utils.geometry_utils import view_points
    from pyquaternion import Quaternion

    sample_data, ego_pose, calibrated = _table("sample_data"), _table("ego_pose"), _table("calibrated_sensor")
    keyframes = {}
    for sd in sample_data.values():
        if sd["is_key_frame"]:
            keyframes[(sd["sample_token"], sd["filename"].split("/")[1])] = sd
    compared = 0
    for i in (0, 20, 40):
        k, rig = drive[i], drive.rig(i)
        for c, name in enumerate(CAMERA_NAMES):
            # the devkit's chain (map_pointcloud_to_image) in float64, with its geometry functions
            lid, cam = keyframes[(k.token, "LIDAR_TOP")], keyframes[(k.token, name)]
            pc = LidarPointCloud.from_file(str(DRIVE / lid["filename"]))
            pc.points = pc.points.astype(np.float64)
            for record, inverse in (
                (calibrated[lid["calibrated_sensor_token"]], False),
                (ego_pose[lid["ego_pose_token"]], False),
                (ego_pose[cam["ego_pose_token"]], True),
                (calibrated[cam["calibrated_sensor_token"]], True),
            ):
                rot = Quaternion(record["rotation"]).rotation_matrix
                if inverse:
                    pc.translate(-np.array(record["translation"]))
                    pc.rotate(rot.T)
                else:
                    pc.rotate(rot)
                    pc.translate(np.array(record["translation"]))
            depth = pc.points[2]
            devkit = view_points(
                pc.points[:3], np.array(calibrated[cam["calibrated_sensor_token"]]["camera_intrinsic"]), normalize=True
            )
            # occvo's: the sweep in the ego frame, to the ego at the image's stamp, projected by the rig
            t = drive.ego_at_camera(i, c)
            ego = drive.lidar_in_ego(i) @ t[:3, :3].T + t[:3, 3]
            uv, occvo_depth, visible = rig.project(ego, min_depth=1.0)
            assert visible[c].sum() > 500
            assert np.allclose(occvo_depth[c], depth, atol=1e-9, rtol=0)
            err = np.abs(uv[c][visible[c]] - devkit[:2].T[visible[c]]).max()
            assert err < 1e-6, (i, name, err)
            compared += visible[c].sum()
    assert compared > 20_000
