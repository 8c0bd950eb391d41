"""nuScenes cameras: a tiny camera-only dataset in nuScenes' table format (written here, read by occvo's reader)
replayed with `occvo replay --nuscenes` through the three workers with the model source: one pose a
sample, stamped with the samples' timestamps, and occupancy the network made with the dataset's calibration."""

import argparse
import importlib
import json
import uuid

import numpy as np
import pytest
import torch
from PIL import Image
from scipy.spatial.transform import Rotation

from occvo_core.cameras import CAMERA_NAMES

SAMPLES = 3
FIRST_US = 1_531_883_530_449_377
CAMERA_LAG_US = np.array([12_000, 4_000, 20_000, 37_000, 29_000, 45_000])  # nuScenes' cameras fire one after another


def _tok():
    return uuid.uuid4().hex


def _record(pose):
    x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
    return {"translation": pose[:3, 3].tolist(), "rotation": [w, x, y, z]}


def write_tiny_nuscenes(root, predictor):
    """SAMPLES keyframes of a synthetic town's six rendered cameras as nuScenes' tables and JPEGs; returns the
    sample timestamps (us) and the calibration written (K (6,3,3), cam_to_ego (6,4,4))."""
    from occvo_core.models.image_source import ImageOccupancySource
    from occvo_core.sim import SyntheticScene

    scene = SyntheticScene(seed=0, frames=SAMPLES)
    cams = ImageOccupancySource(scene, predictor)
    tables = {
        k: []
        for k in (
            "category",
            "attribute",
            "visibility",
            "instance",
            "sample_annotation",
            "sensor",
            "calibrated_sensor",
            "ego_pose",
            "log",
            "scene",
            "sample",
            "sample_data",
            "map",
        )
    }
    log, scene_tok = _tok(), _tok()
    (root / "maps").mkdir(parents=True)
    Image.fromarray(np.zeros((8, 8), np.uint8)).save(root / "maps" / "tiny.png")
    tables["map"].append(
        {"token": _tok(), "log_tokens": [log], "category": "semantic_prior", "filename": "maps/tiny.png"}
    )
    tables["log"].append(
        {
            "token": log,
            "logfile": "tiny",
            "vehicle": "n015",
            "date_captured": "2018-07-18",
            "location": "singapore-onenorth",
        }
    )
    _, k, e = cams.camera_frame(0)
    calib = []
    for c, name in enumerate(CAMERA_NAMES):
        sensor, cs = _tok(), _tok()
        tables["sensor"].append({"token": sensor, "channel": name, "modality": "camera"})
        tables["calibrated_sensor"].append(
            {"token": cs, "sensor_token": sensor, **_record(e[c]), "camera_intrinsic": k[c].tolist()}
        )
        calib.append(cs)
    samples = [_tok() for _ in range(SAMPLES)]
    stamps = FIRST_US + np.arange(SAMPLES) * 500_000 + np.array([0, 1_733, -911])[:SAMPLES]
    sd_prev = {name: "" for name in CAMERA_NAMES}
    sd_tokens = [[_tok() for _ in CAMERA_NAMES] for _ in range(SAMPLES)]
    for i, tok in enumerate(samples):
        tables["sample"].append(
            {
                "token": tok,
                "timestamp": int(stamps[i]),
                "scene_token": scene_tok,
                "prev": samples[i - 1] if i else "",
                "next": samples[i + 1] if i + 1 < SAMPLES else "",
            }
        )
        images, _, _ = cams.camera_frame(i)
        for c, name in enumerate(CAMERA_NAMES):
            when = int(stamps[i] + CAMERA_LAG_US[c])
            rel = f"samples/{name}/n015-2018-07-18-11-07-57+0800__{name}__{when}.jpg"
            (root / rel).parent.mkdir(parents=True, exist_ok=True)
            Image.fromarray(images[c]).save(root / rel, quality=92)
            ego = _tok()
            tables["ego_pose"].append({"token": ego, "timestamp": when, **_record(scene.gt_poses[i])})
            tables["sample_data"].append(
                {
                    "token": sd_tokens[i][c],
                    "sample_token": tok,
                    "ego_pose_token": ego,
                    "calibrated_sensor_token": calib[c],
                    "timestamp": when,
                    "fileformat": "jpg",
                    "is_key_frame": True,
                    "height": images[c].shape[0],
                    "width": images[c].shape[1],
                    "filename": rel,
                    "prev": sd_prev[name],
                    "next": sd_tokens[i + 1][c] if i + 1 < SAMPLES else "",
                }
            )
            sd_prev[name] = sd_tokens[i][c]
    tables["scene"].append(
        {
            "token": scene_tok,
            "log_token": log,
            "nbr_samples": SAMPLES,
            "name": "scene-0061",
            "first_sample_token": samples[0],
            "last_sample_token": samples[-1],
            "description": "tiny",
        }
    )
    (root / "v1.0-mini").mkdir()
    for name, rows in tables.items():
        (root / "v1.0-mini" / f"{name}.json").write_text(json.dumps(rows))
    return stamps, k, e


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    """A freshly initialised `tiny` TPV-Former, saved as `occvo train-occ` saves one (no trained model ships)."""
    from occvo_core.models.tpvformer import TPVFormer, preset, save_checkpoint

    torch.manual_seed(0)
    return save_checkpoint(tmp_path_factory.mktemp("ckpt") / "tiny.pt", TPVFormer(preset("tiny")), {"preset": "tiny"})


@pytest.fixture(scope="module")
def dataset(tmp_path_factory, checkpoint):
    from occvo_core.models.tpvformer.predictor import OccupancyPredictor

    root = tmp_path_factory.mktemp("nuscenes")
    return root, *write_tiny_nuscenes(root, OccupancyPredictor(checkpoint))


def test_the_reader_gives_calibration_and_stamps(dataset):
    from occvo_core.datasets.nuscenes_drive import NuScenesDrive
    from occvo_core.errors import DatasetError
    from occvo_services.nuscenes_source import NuScenesCameraFrames

    root, stamps, k, e = dataset
    scene = NuScenesDrive(root, "scene-0061", "v1.0-mini")
    assert len(scene) == SAMPLES and np.array_equal(scene.stamps, stamps / 1e6)
    s = scene[1]
    assert np.allclose(s.intrinsics, k) and np.allclose(s.cam_to_ego, e, atol=1e-9)
    assert np.array_equal(s.camera_stamps, (stamps[1] + CAMERA_LAG_US) / 1e6)
    frame = NuScenesCameraFrames(root, "v1.0-mini", "scene-0061")[2]
    assert frame.stamp == stamps[2] / 1e6 and [im.camera for im in frame.images] == list(CAMERA_NAMES)
    assert frame.images[3].stamp == (stamps[2] + CAMERA_LAG_US[3]) / 1e6 and frame.images[0].encoding == "jpeg"
    assert s.lidar_file is None and np.allclose(scene.gt_poses[1], s.camera_ego_poses[0])  # camera-only: CAM_FRONT's
    with pytest.raises(DatasetError, match="no scene 'scene-0103'"):
        NuScenesDrive(root, "scene-0103")
    with pytest.raises(DatasetError, match="v1.0-trainval"):
        NuScenesDrive(root, "scene-0061", "v1.0-trainval")


def test_replay_nuscenes_through_the_three_workers_with_the_model_source(dataset, checkpoint, tmp_path, capsys):
    from occvo_core.models.tpvformer.predictor import OccupancyPredictor
    from occvo_core.trajectory import read_tum
    from occvo_schemas import keys
    from occvo_schemas.codec import decode
    from occvo_schemas.models import OccupancyFrameMsg
    from occvo_services.client import OccVOClient
    from occvo_services.local import InProcessService
    from occvo_services.nuscenes_source import NuScenesCameraFrames
    from occvo_services.occupancy_model import camera_inputs
    from occvo_services.sessions import open_session

    root, stamps, _, _ = dataset
    got = {}
    with InProcessService(source="model", checkpoint=str(checkpoint)) as svc:
        session = open_session(svc.endpoint)
        sub = session.declare_subscriber(
            keys.occupancy("nus"),
            lambda s: got.setdefault((m := decode(s.payload.to_bytes(), OccupancyFrameMsg)).seq, m),
        )
        code = _run(
            "replay",
            [
                "--nuscenes",
                str(root),
                "--version",
                "v1.0-mini",
                "--scene",
                "scene-0061",
                "--connect",
                svc.endpoint,
                "--stream",
                "nus",
                "--json",
                "--quiet",
                "--tum",
                str(tmp_path / "t.tum"),
                "--timeout",
                "600",
            ],
        )
        out = capsys.readouterr()
        assert code == 0, out.err
        with OccVOClient(svc.endpoint, stream="nus") as client:
            traj = client.trajectory()
        sub.undeclare()
        session.close()
    assert json.loads(out.out.splitlines()[-1])["poses"] == SAMPLES
    assert np.array_equal(traj.stamps.to_numpy(), stamps / 1e6)
    assert np.allclose(read_tum(tmp_path / "t.tum")[0], stamps / 1e6, rtol=0, atol=2e-6)
    # the worker's occupancy is the network's on those JPEGs with the dataset's calibration, voxel for voxel
    predictor = OccupancyPredictor(checkpoint)
    frames = NuScenesCameraFrames(root, "v1.0-mini", "scene-0061")
    for i in range(SAMPLES):
        images, k, e = camera_inputs(frames[i].images)
        grid = predictor.predict_grid(images, k, e)
        served = np.full(grid.shape, 17, np.uint8)
        served[tuple(got[i].occupancy.voxels.to_numpy().astype(int).T)] = got[i].occupancy.labels.to_numpy()
        assert got[i].stamp == stamps[i] / 1e6 and got[i].source.startswith("model:")
        assert np.array_equal(served, grid), f"sample {i}: {np.count_nonzero(served != grid)} voxels differ"
    # and that calibration matters: the rig turned by 90 degrees gives the network other voxels
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    assert not np.array_equal(predictor.predict_grid(images, k, turn @ e), grid)


def _run(name, argv):
    mod = importlib.import_module(f"occvo_services.commands.{name}")
    parser = argparse.ArgumentParser()
    mod.add_parser(parser.add_subparsers())
    args = parser.parse_args([name, *argv])
    return args.func(args)
