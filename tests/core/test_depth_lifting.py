"""Depth lifting: a pixel's most likely depth goes back along its own ray into the ego frame, the voxels it lands in
are the only occupied ones at inference (with the decoder's best occupied class), training is left as it was, and a
checkpoint carries the setting."""

import math

import numpy as np
import pytest
import torch

from occvo_core.cameras import nuscenes_rig
from occvo_core.grid import FREE, OCC3D_GRID
from occvo_core.models.tpvformer import TPVFormer, load_checkpoint, preset, save_checkpoint
from occvo_core.models.tpvformer.checkpoint import save_half
from occvo_core.models.tpvformer.lifting import lifted_points, lifted_voxels

RANGE = (1.0, 80.0)


def _one_hot_depth(depth: float, bins: int = 32, shape=(6, 14, 25)) -> torch.Tensor:
    b = int(math.log(depth / RANGE[0]) / math.log(RANGE[1] / RANGE[0]) * bins)
    prob = torch.zeros(shape[0], bins, *shape[1:])
    prob[:, b] = 1.0
    centre = RANGE[0] * math.exp((b + 0.5) * math.log(RANGE[1] / RANGE[0]) / bins)
    return prob, centre


def test_a_lifted_pixel_lands_on_its_own_ray_at_its_bin_s_depth():
    rig = nuscenes_rig(200, 112)
    prob, centre = _one_hot_depth(10.0)
    k, e = torch.tensor(rig.intrinsics, dtype=torch.float32), torch.tensor(rig.cam_to_ego, dtype=torch.float32)
    points = lifted_points(prob, k, e, (112, 200), RANGE, upsample=2)  # (6, 28, 50, 3)
    assert points.shape == (6, 28, 50, 3)
    flat = points.reshape(6, -1, 3).numpy().astype(np.float64)
    for c in range(6):
        uv, z, seen = rig.project(flat[c])
        assert seen[c].all()
        assert np.allclose(z[c], centre, rtol=1e-4)  # depth along the optical axis: the bin's centre
        rows, cols = np.meshgrid(np.arange(28), np.arange(50), indexing="ij")
        want = np.stack([(cols + 0.5) * 4 - 0.5, (rows + 0.5) * 4 - 0.5], -1).reshape(-1, 2)
        assert np.allclose(uv[c], want, atol=1e-2)  # back onto the pixel it came from


def test_lifted_voxels_hold_the_points_within_range_only():
    points = torch.tensor([[5.1, 0.1, 0.3], [25.0, 0.0, 0.3], [100.0, 0.0, 0.0], [5.1, 0.1, 0.35]])
    grid = lifted_voxels(points, OCC3D_GRID.lower, OCC3D_GRID.upper, OCC3D_GRID.shape, max_range=20.0)
    assert grid.sum() == 1  # the far one out of range, the last one in the first one's voxel, the third off the grid
    i, j, k = (np.floor((np.array([5.1, 0.1, 0.3]) - OCC3D_GRID.lower) / OCC3D_GRID.voxel_size)).astype(int)
    assert grid[i, j, k]
    assert lifted_voxels(points, OCC3D_GRID.lower, OCC3D_GRID.upper, OCC3D_GRID.shape, max_range=30.0).sum() == 2


def test_a_lifting_model_predicts_occupied_only_where_pixels_land_and_trains_as_before():
    torch.manual_seed(0)
    cfg = preset("tiny")
    plain = TPVFormer(cfg).eval()
    lifting = TPVFormer(cfg.model_copy(update={"lift_range": 30.0})).eval()
    lifting.load_state_dict(plain.state_dict())
    rig = nuscenes_rig(*cfg.input_size)
    x = torch.rand(1, 6, 3, 112, 200)
    k, e = (
        torch.tensor(rig.intrinsics, dtype=torch.float32)[None],
        torch.tensor(rig.cam_to_ego, dtype=torch.float32)[None],
    )
    with torch.no_grad():
        planes, depth_prob = plain.encode_with_depth(x, k, e)
        raw = plain.decode(planes)
        lifted = lifting(x, k, e)
    hit = lifted_voxels(
        lifted_points(depth_prob[0], k[0], e[0], (112, 200), cfg.depth_range, cfg.lift_upsample),
        cfg.lower,
        cfg.upper,
        cfg.grid_shape,
        30.0,
    )
    labels = lifted[0].argmax(0)
    assert hit.any() and torch.equal(labels != FREE, hit)
    assert torch.equal(labels[hit], raw[0, :FREE].argmax(0)[hit])  # the decoder's best occupied class there
    lifting.train()
    with torch.no_grad():
        assert torch.equal(lifting(x, k, e), plain.train()(x, k, e))  # training sees the decoder's own logits


def test_a_checkpoint_carries_the_lifting_range_and_refuses_a_bad_one(tmp_path):
    model = TPVFormer(preset("tiny"))
    src = save_checkpoint(tmp_path / "full.pt", model)
    dst = save_half(src, tmp_path / "half.pt", free_logit_bias=1.0, lift_range=20.0)
    back = load_checkpoint(dst)
    assert back.cfg.lift_range == 20.0 and back.cfg.free_logit_bias == 1.0
    assert back.meta["lift_range_chosen"] == 20.0
    with pytest.raises(ValueError):
        save_half(src, tmp_path / "bad.pt", lift_range=-1.0)
    with pytest.raises(ValueError, match="depth head"):
        preset("paper", lift_range=20.0)  # ConfigError is a ValueError
