"""Training on a real drive: projected LiDAR as the image branch's depth target (on the pixels the points land on,
the nearest point of a pixel kept), augmentation whose intrinsics follow the crop and zoom (a point stays on the same
image content), a mixed run resumed, and the real-rig model as the default wherever the input is a real drive."""

import numpy as np
import pytest
import torch
from nuscenes_sample import DRIVE, drive_root

from occvo_core.cameras import nuscenes_rig
from occvo_core.models.drive_training import NO_LABEL, Augment, DriveFrames, lidar_targets

STILL = Augment(exposure=(1, 1), gamma=(1, 1), white_balance=0.0, saturation=(1, 1), zoom=(1.1, 1.3), noise=0.0)


def _frames(points: np.ndarray, size=(100, 56)) -> DriveFrames:
    """One keyframe of a made-up drive: stored images (twice `size`) whose red and green are the pixel's own
    column and row (content that says where it was), the nuScenes rig, `points` as the sweep."""
    sw, sh = 2 * size[0], 2 * size[1]
    rig = nuscenes_rig(sw, sh)
    u, v = np.meshgrid(np.arange(sw), np.arange(sh))
    image = np.stack([u * 255 // (sw - 1), v * 255 // (sh - 1), np.zeros_like(u)], -1).astype(np.uint8)
    arrays = {
        "scene": np.asarray("made-up"),
        "keyframes": np.array([0]),
        "images": np.broadcast_to(image, (1, 6, sh, sw, 3)).copy(),
        "intrinsics": rig.intrinsics[None],
        "cam_to_ego": rig.cam_to_ego[None],
        "semantics": np.full((1, 200, 200, 16), 17, np.uint8),
        "mask_camera": np.ones((1, 200, 200, 16), bool),
        "points": points.astype(np.float32),
        "point_labels": np.arange(len(points), dtype=np.uint8) % 17,
        "point_counts": np.array([len(points)]),
        "ego_at_camera": np.broadcast_to(np.eye(4), (1, 6, 4, 4)).copy(),
    }
    return DriveFrames(arrays, size)


def test_a_point_s_depth_lands_on_its_pixel_and_the_nearest_point_of_a_pixel_wins():
    rig = nuscenes_rig(200, 112)
    centre = rig.cam_to_ego[0, :3, 3]
    far, aside = np.array([20.0, 0.3, 1.0]), np.array([15.0, -3.0, 0.0])
    near = centre + 0.5 * (far - centre)
    points = np.stack([far, near, aside])  # far and near on one ray of CAM_FRONT (camera 0)
    labels = np.array([15, 4, 11], np.uint8)
    depth, cls = lidar_targets([points] * 6, [labels] * 6, rig)
    uv, z, seen = rig.project(points)
    assert seen[0].all()
    for p, want in ((1, 4), (2, 11)):
        u, v = np.rint(uv[0, p]).astype(int)
        k, cam = rig.intrinsics[0], np.linalg.inv(rig.cam_to_ego[0])[:3] @ np.append(points[p], 1)
        assert cls[0, v, u] == want
        ray = z[0, p] * np.sqrt(((u - k[0, 2]) / k[0, 0]) ** 2 + ((v - k[1, 2]) / k[1, 1]) ** 2 + 1)
        assert depth[0, v, u] == pytest.approx(ray, rel=1e-5)
        assert depth[0, v, u] == pytest.approx(np.linalg.norm(cam), rel=0.02)  # the point's distance, near enough
    assert np.isfinite(depth[0]).sum() == 2 and (cls[0] != NO_LABEL).sum() == 2  # far is hidden behind near
    assert not np.isfinite(depth[3]).any()  # CAM_BACK sees none of them


def test_a_point_stays_on_the_same_image_content_after_crop_and_zoom():
    rng = np.random.default_rng(3)
    points = np.column_stack([rng.uniform(8, 30, 400), rng.uniform(-6, 6, 400), rng.uniform(-0.5, 2.0, 400)])
    frames = _frames(points)
    stored = frames.rig(0)
    plain = frames.sample(0)
    sample = frames.sample(0, np.random.default_rng(7), STILL)
    k = sample.intrinsics.numpy()
    assert not np.allclose(k[0], plain.intrinsics.numpy()[0])  # the crop moved and zoomed camera 0
    zoom = k[:, :2, :2].diagonal(axis1=1, axis2=2) / plain.intrinsics.numpy()[:, :2, :2].diagonal(axis1=1, axis2=2)
    np.testing.assert_allclose(zoom[:, 0], zoom[:, 1], rtol=1e-5)  # one zoom both ways: the aspect kept
    assert np.all((zoom >= 1.1 - 1e-5) & (zoom <= 1.3 + 1e-5))
    from occvo_core.cameras import CameraRig

    out_rig = CameraRig(k.astype(np.float64), sample.cam_to_ego.numpy().astype(np.float64), (100, 56))
    uv_in, _, seen_in = stored.project(points)
    uv_out, _, seen_out = out_rig.project(points)
    sw, sh = stored.size
    image = sample.images[0].permute(1, 2, 0).numpy()  # CAM_FRONT after augmentation
    ok = seen_out[0] & seen_in[0]
    ok &= (uv_out[0, :, 0] > 1) & (uv_out[0, :, 0] < 98) & (uv_out[0, :, 1] > 1) & (uv_out[0, :, 1] < 54)
    assert ok.sum() > 50
    for (u, v), (u0, v0) in zip(uv_out[0][ok], uv_in[0][ok]):
        # bilinear read of the augmented image at the point's new pixel = the stored column and row it came from
        x0, y0 = int(np.floor(u)), int(np.floor(v))
        fx, fy = u - x0, v - y0
        px = (
            image[y0, x0] * (1 - fx) * (1 - fy)
            + image[y0, x0 + 1] * fx * (1 - fy)
            + image[y0 + 1, x0] * (1 - fx) * fy
            + image[y0 + 1, x0 + 1] * fx * fy
        )
        assert px[0] * (sw - 1) == pytest.approx(u0, abs=1.5)  # within a stored pixel and a half (8-bit steps)
        assert px[1] * (sh - 1) == pytest.approx(v0, abs=1.5)
    # and the depth target sits where the augmented rig puts the points
    u, v = np.rint(uv_out[0][ok]).astype(int).T
    assert np.isfinite(sample.depth[0][v, u]).all()


def test_photometric_augmentation_changes_colours_but_never_the_geometry():
    frames = _frames(np.array([[10.0, 0.0, 0.5]]))
    a = frames.sample(0, np.random.default_rng(1), Augment(zoom=(1.0, 1.0)))
    b = frames.sample(0)
    np.testing.assert_allclose(a.intrinsics, b.intrinsics, rtol=1e-6)
    assert not torch.allclose(a.images, b.images, atol=0.02)
    assert a.images.min() >= 0 and a.images.max() <= 1


def test_frames_survive_a_save_and_load(tmp_path):
    frames = _frames(np.array([[10.0, 0.0, 0.5], [12.0, 1.0, 0.0]]))
    back = DriveFrames.load(frames.save(tmp_path / "frames.npz"))
    assert back.input_size == (100, 56) and back.keyframes == [0]
    a, b = frames.sample(0), back.sample(0)
    assert torch.equal(a.images, b.images)
    np.testing.assert_array_equal(a.depth, b.depth)


def test_a_mixed_run_of_real_and_synthetic_frames_resumes_where_it_stopped(tmp_path):
    from occvo_core.models.tpvformer import load_checkpoint, preset
    from occvo_core.models.train import train

    cfg = preset("tiny", input_size=(100, 56))
    rng = np.random.default_rng(0)
    frames = _frames(np.column_stack([rng.uniform(5, 30, 300), rng.uniform(-20, 20, 300), rng.uniform(-1, 2, 300)]))
    frames.arrays["semantics"][0, 100:110, 95:105, 2:5] = 15  # something occupied to learn
    first = train(cfg, tmp_path / "a", 5, [0], frames=2, stride=2, max_steps=2, progress=False, real=frames)
    assert first.steps == 2 and len(first.losses) == 2
    second = train(
        cfg, tmp_path / "b", 5, [0], frames=2, stride=2, max_steps=1, progress=False, real=frames,
        resume=first.checkpoint, meta={"train_drive": {"scene": "made-up", "keyframes": [0, 0]}},
    )  # fmt: skip
    assert second.steps == 3 and second.losses[:2] == first.losses
    model = load_checkpoint(second.checkpoint)
    assert model.meta["steps"] == 3 and model.meta["train_drive"]["scene"] == "made-up"
    assert "free_logit_bias" in model.meta["calibration"]  # calibrated on the real frames


def test_a_depth_only_run_trains_the_image_branch_and_leaves_the_voxel_side_as_it_was(tmp_path):
    from occvo_core.models.tpvformer import TPVFormer, load_checkpoint, preset, save_checkpoint
    from occvo_core.models.train import train

    cfg = preset("tiny", input_size=(100, 56))
    rng = np.random.default_rng(0)
    frames = _frames(np.column_stack([rng.uniform(5, 30, 300), rng.uniform(-20, 20, 300), rng.uniform(-1, 2, 300)]))
    start = save_checkpoint(tmp_path / "start.pt", TPVFormer(cfg))
    result = train(
        cfg, tmp_path / "d", 5, [], max_steps=2, progress=False, real=frames, resume=start, depth_weight=4.0,
        depth_only=True,
    )  # fmt: skip
    before, after = load_checkpoint(start).state_dict(), load_checkpoint(result.checkpoint).state_dict()
    changed = {k.split(".")[0] for k in before if not torch.equal(before[k], after[k])}
    assert changed == {"backbone", "depth_head"}  # queries, attention, decoder untouched
    assert result.steps == 2 and all(np.isfinite(result.losses))


def test_the_real_rig_model_is_the_default_for_a_drive_and_tiny_for_the_synthetic_town():
    from occvo_core.models.tpvformer import load_checkpoint
    from occvo_core.models.tpvformer.checkpoint import REAL_RIG_MODEL, SERVED_THRESHOLDS, served_model

    real, real_thresholds = served_model(real_rig=True)
    town, town_thresholds = served_model(real_rig=False)
    assert real.name == f"{REAL_RIG_MODEL}.pt" and town.name == "tiny.pt"
    assert real_thresholds == SERVED_THRESHOLDS[REAL_RIG_MODEL] and town_thresholds == (0.9, 1.0)
    assert real.stat().st_size <= 5_000_000
    payload = torch.load(real, map_location="cpu", weights_only=True)
    assert {v.dtype for v in payload["state_dict"].values() if v.is_floating_point()} == {torch.float16}
    model = load_checkpoint(real)
    assert model.meta["train_drive"] == {"scene": "scene-0916", "keyframes": [0, 24]}  # 25-40 never trained on
    assert model.cfg.free_logit_bias == model.meta["free_logit_bias_chosen"]  # the offset chosen on 17-24
    assert "train_drive" not in load_checkpoint(town).meta


def test_occvo_run_from_images_takes_the_real_rig_model_on_a_drive_and_tiny_on_the_town():
    drive_root()
    from occvo_cli.cli import build_parser
    from occvo_cli.commands.run import _image_source
    from occvo_core.models.tpvformer.checkpoint import REAL_RIG_MODEL, SERVED_THRESHOLDS

    parser = build_parser()
    drive = _image_source(parser.parse_args(["run", "--input", str(DRIVE), "--from-images", "--threads", "1"]))
    town = _image_source(parser.parse_args(["run", "--from-images", "--threads", "1"]))
    assert drive.predictor.model.meta["train_drive"]["scene"] == "scene-0916"
    assert (drive.predictor.min_confidence, drive.predictor.min_ground_confidence) == SERVED_THRESHOLDS[REAL_RIG_MODEL]
    assert "train_drive" not in town.predictor.model.meta
    assert (town.predictor.min_confidence, town.predictor.min_ground_confidence) == (0.9, 1.0)
