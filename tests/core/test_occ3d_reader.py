"""Occ3D layout reader and the synthetic exports: written scenes read back frame for frame."""

import numpy as np
import pytest

from occvo_core.datasets import open_scene
from occvo_core.datasets.occ3d import Occ3DScene
from occvo_core.datasets.occvo_release import OccVOReleaseScene
from occvo_core.errors import DatasetError, InvalidFrameError
from occvo_core.grid import FREE, OCC3D_GRID
from occvo_core.sim import SyntheticScene
from occvo_core.sim.export import export_occ3d, export_release
from occvo_core.trajectory import write_tum


@pytest.fixture(scope="module")
def scene():
    return SyntheticScene(seed=7, frames=4)


def _same(a, b):
    order_a = np.lexsort(a.points.T)
    order_b = np.lexsort(b.points.T)
    return np.array_equal(a.points[order_a], b.points[order_b]) and np.array_equal(a.labels[order_a], b.labels[order_b])


def test_occ3d_export_reads_back_identically(tmp_path, scene):
    d = export_occ3d(scene, tmp_path / "pred", semantics="prediction")
    back = Occ3DScene(d)
    assert len(back) == len(scene) and back.name == scene.name
    for i in range(len(scene)):
        assert _same(back[i], scene[i]), i
    # the default writes Occ3D's ground truth: the whole noise-free grid, which mask="camera" cuts to the clean frames
    d = export_occ3d(scene, tmp_path)
    back = Occ3DScene(d)
    clean = SyntheticScene(seed=7, frames=4, noise="none")
    for i in range(len(scene)):
        assert _same(back[i], clean[i]), i
    assert np.array_equal(back.load(2)[0], scene.true_grid(2))
    assert len(Occ3DScene(d, mask="none")[1]) > 2 * len(clean[1])
    assert np.allclose(back.gt_poses, scene.gt_poses, atol=1e-8)
    sem, cam, lidar = back.load(0)
    assert sem.dtype == np.uint8 and sem.shape == OCC3D_GRID.shape and cam.any() and lidar.any()
    assert isinstance(open_scene(d), Occ3DScene)
    truth = np.load(d / "truth.npz")
    assert len(truth["static_points"]) == len(truth["static_labels"]) > 0


def test_release_export_reads_back_identically(tmp_path, scene):
    d = export_release(scene, tmp_path)
    back = OccVOReleaseScene(d)
    for i in range(len(scene)):
        assert np.array_equal(back[i].points, scene[i].points) and np.array_equal(back[i].labels, scene[i].labels)
    assert np.allclose(back.gt_poses, scene.gt_poses, atol=1e-8)


def _write(path, **arrays):
    path.mkdir(parents=True, exist_ok=True)
    np.savez(path / "labels.npz", **arrays)


def test_masks_frame_order_and_tum_poses(tmp_path):
    sem = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    sem[10, 10, 2], sem[20, 20, 2], sem[30, 30, 3] = 11, 13, 15
    cam = np.zeros(OCC3D_GRID.shape, np.uint8)
    cam[10, 10, 2] = 1
    lidar = cam.copy()
    lidar[20, 20, 2] = 1
    for name in ("10", "2", "1"):
        _write(tmp_path / "s" / name, semantics=sem, mask_camera=cam, mask_lidar=lidar)
    poses = np.tile(np.eye(4), (3, 1, 1))
    poses[:, 0, 3] = [0, 1, 2]
    write_tum(tmp_path / "p.tum", poses)
    s = Occ3DScene(tmp_path / "s", poses=tmp_path / "p.tum")
    assert [p.parent.name for p in s.files] == ["1", "2", "10"]  # numeric order
    assert len(s[0]) == 1 and s[0].labels.tolist() == [11]
    assert len(Occ3DScene(tmp_path / "s", mask="lidar")[0]) == 2
    assert len(Occ3DScene(tmp_path / "s", mask="none")[0]) == 3
    assert np.allclose(s.gt_poses[:, 0, 3], [0, 1, 2])


def test_bad_files_raise_dataset_errors(tmp_path):
    with pytest.raises(DatasetError):
        Occ3DScene(tmp_path / "nowhere")
    with pytest.raises(DatasetError, match="no <frame>/labels.npz"):
        Occ3DScene(tmp_path)
    _write(tmp_path / "a" / "0", semantics=np.zeros((10, 10, 4), np.uint8))
    with pytest.raises(DatasetError, match="shape"):
        Occ3DScene(tmp_path / "a").load(0)
    _write(tmp_path / "b" / "0", mask_camera=np.ones(OCC3D_GRID.shape, bool))
    with pytest.raises(DatasetError, match="semantics"):
        Occ3DScene(tmp_path / "b").load(0)
    _write(
        tmp_path / "c" / "0",
        semantics=np.full(OCC3D_GRID.shape, 40, np.uint8),
        mask_camera=np.ones(OCC3D_GRID.shape, bool),
    )
    with pytest.raises(DatasetError, match="0..17"):
        Occ3DScene(tmp_path / "c").load(0)
    _write(tmp_path / "d" / "0", semantics=np.full(OCC3D_GRID.shape, 11, np.uint8))
    with pytest.raises(DatasetError, match="mask_camera"):
        Occ3DScene(tmp_path / "d").load(0)
    (tmp_path / "e" / "0").mkdir(parents=True)
    (tmp_path / "e" / "0" / "labels.npz").write_bytes(b"garbage")
    with pytest.raises(DatasetError, match="unreadable"):
        Occ3DScene(tmp_path / "e").load(0)
    with pytest.raises(InvalidFrameError, match="unreadable"):  # as a frame: skippable (--skip-bad-frames)
        Occ3DScene(tmp_path / "e")[0]
    _write(tmp_path / "f" / "tok_a", semantics=np.full(OCC3D_GRID.shape, 11, np.uint8))
    with pytest.raises(DatasetError, match="order"):
        Occ3DScene(tmp_path / "f")
    assert len(Occ3DScene(tmp_path / "f", frames=["tok_a"], mask="none")) == 1
