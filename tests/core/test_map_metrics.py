"""Map metrics on hand-built maps with known answers, map files, the reference map and the eval-map command."""

import numpy as np
import pytest

from occvo_core.errors import DatasetError
from occvo_core.map_metrics import (
    REFERENCE_MAP,
    align_to_ground_truth,
    load_map,
    map_metrics,
    reference_map_from_poses,
    save_map,
    voxel_downsample,
)


def _line(n, z=0.0):
    return np.column_stack([np.arange(n) * 1.0, np.zeros(n), np.full(n, z)])


def test_identical_maps_are_perfect():
    pts = _line(10)
    m = map_metrics(pts, np.full(10, 15), pts, np.full(10, 15))
    assert (m.accuracy, m.precision, m.completion) == (0.0, 1.0, 1.0)
    assert m.n_reconstructed == m.n_ground_truth == 10


def test_known_offsets_give_known_numbers():
    gt = _line(10)  # points 1 m apart
    est = gt[:5] + [0, 0.3, 0]  # half the map, 0.3 m off
    est = np.vstack([est, [[0, 0.6, 0], [20, 0, 0]]])  # one 0.6 m off, one 10 m off (nearest gt at x=9 -> 11 m)
    m = map_metrics(est, None, gt, None)
    d = np.array([0.3] * 5 + [0.6, 11.0])
    assert m.accuracy == pytest.approx(np.sqrt(np.mean(d**2)))
    assert m.precision == pytest.approx(5 / 7)
    assert m.completion == pytest.approx(5 / 10)  # x = 0..4 have an est point within 0.4 m


def test_threshold_is_inclusive_and_configurable():
    gt = _line(3)
    est = gt + [0, 0.4, 0]
    assert map_metrics(est, None, gt, None).precision == 1.0
    assert map_metrics(est, None, gt, None, threshold=0.39).precision == 0.0


def test_static_classes_only_by_default():
    gt = _line(4)
    gt_labels = np.array([11, 11, 4, 4])  # road, road, car, car
    est = gt[:2]
    est_labels = np.array([11, 11])
    m = map_metrics(est, est_labels, gt, gt_labels)
    assert m.completion == 1.0 and m.n_ground_truth == 2  # the parked cars do not count
    assert map_metrics(est, est_labels, gt, gt_labels, classes=None).completion == 0.5


def test_empty_maps_do_not_crash():
    m = map_metrics(np.zeros((0, 3)), None, _line(3), None)
    assert np.isnan(m.accuracy) and m.precision == 0.0 and m.completion == 0.0


def test_voxel_downsample_majority_label():
    pts = np.array([[0.1, 0.1, 0.1], [0.2, 0.2, 0.2], [0.3, 0.1, 0.1], [1.0, 1.0, 1.0]])
    p, l = voxel_downsample(pts, np.array([15, 16, 16, 11]), 0.4)
    assert len(p) == 2
    assert np.allclose(p[0], [0.2, 0.2, 0.2]) and l[0] == 16 and l[1] == 11


def test_alignment_undoes_a_rigid_motion():
    rng = np.random.default_rng(0)
    gt_poses = np.tile(np.eye(4), (6, 1, 1))
    gt_poses[:, :3, 3] = np.column_stack([np.arange(6) * 2.0, np.sin(np.arange(6)), np.zeros(6)])
    t = np.eye(4)
    c, s = np.cos(0.7), np.sin(0.7)
    t[:3, :3] = [[c, -s, 0], [s, c, 0], [0, 0, 1]]
    t[:3, 3] = [5, -3, 1]
    est_poses = np.linalg.inv(t) @ gt_poses
    pts = rng.uniform(-10, 10, (50, 3))
    est_pts = pts @ np.linalg.inv(t)[:3, :3].T + np.linalg.inv(t)[:3, 3]
    assert np.allclose(align_to_ground_truth(est_pts, est_poses, gt_poses), pts, atol=1e-9)


@pytest.mark.parametrize("suffix", [".npz", ".ply"])
def test_map_files_round_trip(tmp_path, suffix):
    pts = np.random.default_rng(1).uniform(-5, 5, (20, 3))
    labels = np.arange(20, dtype=np.uint8) % 17
    save_map(tmp_path / f"m{suffix}", pts, labels)
    m = load_map(tmp_path / f"m{suffix}")
    assert np.array_equal(m.points, pts) and np.array_equal(m.labels, labels)


def test_ascii_ply_and_bad_files(tmp_path):
    (tmp_path / "a.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nproperty uchar label\nend_header\n0 0 0 11\n1 2 3 15\n"
    )
    m = load_map(tmp_path / "a.ply")
    assert m.points.tolist() == [[0, 0, 0], [1, 2, 3]] and m.labels.tolist() == [11, 15]
    (tmp_path / "b.npz").write_bytes(b"not a zip")
    with pytest.raises(DatasetError):
        load_map(tmp_path / "b.npz")
    np.savez(tmp_path / "c.npz", xyz=np.zeros((3, 3)))
    with pytest.raises(DatasetError, match="points"):
        load_map(tmp_path / "c.npz")
    with pytest.raises(DatasetError):
        load_map(tmp_path / "missing.ply")


def test_reference_map_from_synthetic_poses_matches_the_frames():
    from occvo_core.sim import SyntheticScene

    s = SyntheticScene(seed=2, frames=4, noise="none")
    ref = reference_map_from_poses(s)
    assert ref.kind == REFERENCE_MAP
    points, labels = ref
    truth, truth_labels = s.static_map()
    m = map_metrics(points, labels, truth, truth_labels)
    assert m.precision > 0.97 and m.completion > 0.97


def test_eval_map_command(tmp_path, capsys):
    from occvo_cli.commands import eval_map

    gt = _line(10)
    save_map(tmp_path / "gt.npz", gt, np.full(10, 15))
    save_map(tmp_path / "est.ply", gt[:5] + [0, 0.1, 0], np.full(5, 15))
    import argparse

    parser = argparse.ArgumentParser()
    eval_map.add_parser(parser.add_subparsers())
    args = parser.parse_args(
        ["eval-map", "--gt-map", str(tmp_path / "gt.npz"), "--est-map", str(tmp_path / "est.ply"), "--json"]
    )
    assert args.func(args) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    assert out["precision"] == 1.0 and out["completion"] == 0.5 and out["accuracy"] == pytest.approx(0.1)


def test_alignment_is_well_posed_on_a_straight_drive():
    gt_poses = np.tile(np.eye(4), (8, 1, 1))
    gt_poses[:, 0, 3] = np.arange(8) * 3.0  # a straight line: positions alone leave the roll about x free
    t = np.eye(4)
    c, s = np.cos(0.3), np.sin(0.3)
    t[:3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]
    t[:3, 3] = [1, 2, 3]
    inv = np.linalg.inv(t)
    pts = np.random.default_rng(2).uniform(-20, 20, (30, 3))
    est_pts = pts @ inv[:3, :3].T + inv[:3, 3]
    assert np.allclose(align_to_ground_truth(est_pts, inv @ gt_poses, gt_poses), pts, atol=1e-8)
