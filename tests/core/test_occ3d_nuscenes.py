"""Occ3D-nuScenes as released (gts/<scene>/<sample_token>/labels.npz + annotations.json), built from the real
sample: frames in prev/next order, ego poses as ground truth, timestamps as stamps, against the release format."""

import json
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from occvo_core.datasets import open_scene
from occvo_core.datasets.occ3d_nuscenes import list_scenes
from occvo_core.datasets.occvo_release import OccVOReleaseScene, write_release_scene
from occvo_core.envs.replay import ReplayEnv
from occvo_core.errors import DatasetError
from occvo_core.eval import ape_rmse
from occvo_core.grid import FREE, OCC3D_GRID, grid_to_points, points_to_grid
from occvo_core.pipeline import OdometryPipeline
from occvo_core.trajectory import read_kitti, read_tum

CAMERAS = ("CAM_FRONT", "CAM_FRONT_RIGHT", "CAM_FRONT_LEFT", "CAM_BACK", "CAM_BACK_LEFT", "CAM_BACK_RIGHT")
FIRST_STAMP_US = 1_533_151_603_547_590  # a nuScenes-like clock: ~0.5 s apart, not evenly


def _ego_pose(pose):
    x, y, z, w = Rotation.from_matrix(pose[:3, :3]).as_quat()
    return {"translation": pose[:3, 3].tolist(), "rotation": [w, x, y, z]}


def _grids(source):
    """Each release frame as Occ3D's dense grid; the lidar mask leaves out the upper half to tell the masks apart."""
    for i in range(len(source)):
        f = source[i]
        sem = points_to_grid(f.points, f.labels)
        cam = sem != FREE
        lidar = cam.copy()
        lidar[:, :, 8:] = False
        yield sem, cam, lidar


def build_release_tree(root, sample_root, scenes, rng):
    """Occ3D-nuScenes' layout with shuffled token names and a shuffled annotations.json; returns the stamps (us)."""
    infos, stamps = {}, {}
    for name, n in scenes.items():
        src = OccVOReleaseScene(sample_root / "occupancy" / name)
        n = n or len(src)
        tokens = [rng.bytes(16).hex() for _ in range(n)]
        us = FIRST_STAMP_US + np.cumsum(rng.integers(490_000, 510_000, n))
        stamps[name] = us
        samples = {}
        for i, (tok, (sem, cam, lidar)) in enumerate(zip(tokens, _grids(src))):
            d = root / "gts" / name / tok
            d.mkdir(parents=True)
            np.savez_compressed(
                d / "labels.npz", semantics=sem, mask_camera=cam.astype(np.uint8), mask_lidar=lidar.astype(np.uint8)
            )
            samples[tok] = {
                "timestamp": int(us[i]),
                "ego_pose": _ego_pose(src.gt_poses[i]),
                "prev": tokens[i - 1] if i else "EOF",
                "next": tokens[i + 1] if i + 1 < n else "EOF",
                "gt_path": f"./data/occ3d-nus/gts/{name}/{tok}/labels.npz",
                "camera_sensor": {
                    cam_name: {
                        "img_path": f"./data/nuscenes/samples/{cam_name}/{tok}.jpg",
                        "intrinsics": [[1266.4, 0, 816.3], [0, 1266.4, 491.5], [0, 0, 1]],
                        "extrinsic": {"translation": [1.7, 0.0, 1.5], "rotation": [0.5, -0.5, 0.5, -0.5]},
                        "ego_pose": _ego_pose(src.gt_poses[i]),
                    }
                    for cam_name in CAMERAS
                },
            }
        keys = list(samples)
        rng.shuffle(keys)  # dict order says nothing: only the chain does
        infos[name] = {k: samples[k] for k in keys}
    (root / "annotations.json").write_text(
        json.dumps({"train_split": [], "val_split": list(scenes), "scene_infos": infos})
    )
    return stamps


@pytest.fixture(scope="module")
def tree(sample_root, tmp_path_factory):
    root = tmp_path_factory.mktemp("occ3d-nus")
    stamps = build_release_tree(root, sample_root, {"scene-0101": None, "scene-0268": 5}, np.random.default_rng(30))
    return root, stamps


def test_token_tree_reads_in_chain_order_with_ego_poses_and_stamps(tree, sample_root):
    root, stamps = tree
    assert [s["scene"] for s in list_scenes(root)] == ["scene-0101", "scene-0268"]
    src = OccVOReleaseScene(sample_root / "occupancy" / "scene-0101")
    scene = open_scene(root, scene="scene-0101")
    assert len(scene) == len(src) == 40
    assert np.allclose(scene.gt_poses, src.gt_poses, atol=1e-9)
    assert [scene[i].stamp for i in (0, 17, 39)] == [stamps["scene-0101"][i] / 1e6 for i in (0, 17, 39)]
    for i in (0, 23):
        sem = points_to_grid(src[i].points, src[i].labels)
        assert np.array_equal(scene.load(i)[0], sem), i
    # the gts/<scene> folder alone finds its root's annotations; the masks are an option
    assert open_scene(root / "gts" / "scene-0268").gt_poses.shape == (5, 4, 4)
    assert len(open_scene(root, scene="scene-0101", mask="lidar")[3]) < len(scene[3])
    env = ReplayEnv(root / "gts" / "scene-0101")
    _, info = env.reset()
    assert info["stamp"] == stamps["scene-0101"][0] / 1e6 and np.allclose(info["gt_pose"], src.gt_poses[0])
    with pytest.raises(DatasetError, match="--scene"):
        open_scene(root)
    with pytest.raises(DatasetError, match="no scene 'scene-9999'"):
        open_scene(root, scene="scene-9999")


def test_broken_chains_are_named(tmp_path, tree):
    root, _ = tree
    infos = json.loads((root / "annotations.json").read_text())["scene_infos"]
    samples = infos["scene-0268"]
    first = next(t for t, s in samples.items() if s["prev"] == "EOF")
    for case, edit, match in [
        ("loop", lambda s: s[samples[first]["next"]].update(next=first), "loops"),
        ("two heads", lambda s: s[samples[first]["next"]].update(prev="EOF"), "one first sample"),
        ("no stamp", lambda s: s[first].pop("timestamp"), "timestamp"),
    ]:
        broken = json.loads(json.dumps(samples))
        edit(broken)
        d = tmp_path / case.replace(" ", "_")
        (d / "gts").mkdir(parents=True)
        (d / "gts" / "scene-0268").symlink_to(root / "gts" / "scene-0268")
        (d / "annotations.json").write_text(json.dumps({"scene_infos": {"scene-0268": broken}}))
        with pytest.raises(DatasetError, match=match):
            open_scene(d, scene="scene-0268")


def test_cli_lists_scenes_and_writes_the_annotation_stamps(tree, tmp_path):
    root, stamps = tree
    listed = subprocess.run(
        [sys.executable, "-m", "occvo_cli", "run", "--input", str(root), "--list-scenes"],
        check=False,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert listed.returncode == 0, listed.stderr
    assert [json.loads(line)["scene"] for line in listed.stdout.splitlines()] == ["scene-0101", "scene-0268"]
    out = tmp_path / "out"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "occvo_cli",
            "run",
            "--input",
            str(root),
            "--scene",
            "scene-0268",
            "--out",
            str(out),
            "--quiet",
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    tum_stamps, tum_poses = read_tum(out / "trajectory.tum")
    assert np.allclose(tum_stamps, stamps["scene-0268"] / 1e6, rtol=0, atol=2e-6)  # microseconds survive the file
    assert np.allclose(tum_poses, read_kitti(out / "trajectory.kitti"), atol=1e-6)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["frames"] == 5 and summary["success"] is True


def test_token_tree_runs_like_the_release_format_and_the_original(tree, sample_root, tmp_path):
    root, _ = tree
    token_scene = open_scene(root, scene="scene-0101")
    tokens = OdometryPipeline(token_scene, progress=False).run().odometry.poses
    # the same grids (camera mask) in the release format: the same trajectory to the last bits
    frames = []
    for i in range(len(token_scene)):
        sem, cam, _ = token_scene.load(i)
        frames.append(type(token_scene[i])(*grid_to_points(sem, OCC3D_GRID, cam), index=i))
    same = OccVOReleaseScene(write_release_scene(tmp_path / "release", "scene-0101", frames))
    same_poses = OdometryPipeline(same, progress=False).run().odometry.poses
    difference = np.max(np.linalg.norm(same_poses[:, :3, 3] - tokens[:, :3, 3], axis=1))
    # the original release files (coordinates off the grid centres in the last bits): APE within 0.05 m of theirs
    original = OccVOReleaseScene(sample_root / "occupancy" / "scene-0101")
    theirs = ape_rmse(original.gt_poses, OdometryPipeline(original, progress=False).run().odometry.poses)
    ours = ape_rmse(token_scene.gt_poses, tokens)
    print(
        f"scene-0101: token tree vs release format {difference:.3g} m; APE token tree {ours:.4f} m, "
        f"original release {theirs:.4f} m"
    )
    assert difference <= 1e-9
    assert abs(ours - theirs) <= 0.05


def test_service_carries_the_annotation_stamps_to_poses_trajectory_and_tum(tree, tmp_path, capsys):
    """occvo replay of the token tree through the three workers: every pose, the trajectory query and the TUM file
    carry annotations.json's timestamps."""
    from occvo_services.client import OccVOClient
    from occvo_services.local import InProcessService

    root, stamps = tree
    want = stamps["scene-0268"] / 1e6
    with InProcessService() as svc:
        code = _run_command(
            "replay",
            [
                str(root),
                "--scene",
                "scene-0268",
                "--connect",
                svc.endpoint,
                "--stream",
                "occ3d",
                "--tum",
                str(tmp_path / "t.tum"),
                "--timeout",
                "300",
            ],
        )
        assert code == 0, capsys.readouterr().err
        with OccVOClient(svc.endpoint, stream="occ3d") as client:
            traj = client.trajectory()
    assert np.allclose(traj.stamps.to_numpy(), want, rtol=0, atol=1e-9)
    tum_stamps, _ = read_tum(tmp_path / "t.tum")
    assert np.allclose(tum_stamps, want, rtol=0, atol=2e-6)


def _run_command(name, argv):
    import argparse
    import importlib

    mod = importlib.import_module(f"occvo_services.commands.{name}")
    parser = argparse.ArgumentParser()
    mod.add_parser(parser.add_subparsers())
    args = parser.parse_args([name, *argv])
    return args.func(args)
