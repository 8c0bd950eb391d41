"""The label prior: the training labels' per-voxel occupancy frequency as a learned offset of the free logit, added
to a trained checkpoint without one and trained on from there."""

import numpy as np
import pytest
import torch
from test_drive_training import _frames

from occvo_core.grid import FREE
from occvo_core.models.label_prior import free_prior, occupancy_frequency, with_label_prior


def test_a_voxel_often_occupied_gets_a_negative_free_offset_and_one_never_occupied_a_positive_one():
    semantics = np.full((4, 200, 200, 16), FREE, np.uint8)
    semantics[:3, 100:102, 100:102, 3] = 15  # 3 keyframes of 4
    semantics[0, 10:12, 10:12, 3] = 15  # 1 of 4
    frequency = occupancy_frequency(semantics)
    assert frequency[100, 100, 3] == 0.75 and frequency[10, 10, 3] == 0.25 and frequency[0, 0, 0] == 0
    prior = free_prior(frequency, (100, 100, 16), threshold=0.4, weight=1.0)
    assert prior.shape == (100, 100, 16)
    assert prior[50, 50, 3] < 0 < prior[5, 5, 3] < prior[0, 0, 0] <= 4.0  # 0.75 occupied, 0.25 and 0 free
    half = free_prior(frequency, (100, 100, 16), 0.4, 0.5)
    assert half[50, 50, 3] == pytest.approx(prior[50, 50, 3] / 2) and half[0, 0, 0] < prior[0, 0, 0]
    with pytest.raises(ValueError, match="threshold"):
        free_prior(frequency, (100, 100, 16), threshold=1.0, weight=1.0)
    with pytest.raises(ValueError, match="label grids"):
        occupancy_frequency(semantics[0])


def test_the_prior_moves_only_the_free_logit_and_survives_a_checkpoint(tmp_path):
    from occvo_core.models.tpvformer import TPVFormer, load_checkpoint, preset, save_checkpoint

    cfg = preset("tiny", input_size=(100, 56))
    start = save_checkpoint(tmp_path / "start.pt", TPVFormer(cfg))
    prior = torch.zeros(100, 100, 16)
    prior[40:60, 40:60, 2:4] = -3.0
    model = load_checkpoint(with_label_prior(start, tmp_path / "prior.pt", prior))
    plain = load_checkpoint(start)
    frames = _frames(np.array([[10.0, 0.0, 0.5]]))
    s = frames.sample(0)
    with torch.no_grad():
        a, b = (m(s.images[None], s.intrinsics[None], s.cam_to_ego[None])[0] for m in (model, plain))
    torch.testing.assert_close(a[:FREE], b[:FREE])  # the occupied classes as before
    assert (a[FREE] - b[FREE]).min() < -2.5 and torch.equal(a[FREE, :60, :60], b[FREE, :60, :60])  # the block only


def test_a_run_adds_the_prior_to_a_checkpoint_without_one_and_resumes_it_after(tmp_path):
    from occvo_core.models.tpvformer import TPVFormer, load_checkpoint, preset, save_checkpoint
    from occvo_core.models.train import train

    cfg = preset("tiny", input_size=(100, 56))
    rng = np.random.default_rng(0)
    frames = _frames(np.column_stack([rng.uniform(5, 30, 300), rng.uniform(-20, 20, 300), rng.uniform(-1, 2, 300)]))
    frames.arrays["semantics"][0, 100:110, 95:105, 2:5] = 15
    start = save_checkpoint(tmp_path / "start.pt", TPVFormer(cfg))
    prior = free_prior(occupancy_frequency(frames.arrays["semantics"]), (100, 100, 16), 0.4, 1.0)
    with_prior = cfg.model_copy(update={"label_prior": True})
    first = train(with_prior, tmp_path / "a", 5, [], max_steps=2, progress=False, real=frames, resume=start,
                  label_prior=prior)  # fmt: skip
    model = load_checkpoint(first.checkpoint)
    assert model.cfg.label_prior and first.steps == 2
    moved = model.free_prior.detach()
    assert not torch.equal(moved, prior) and (moved - prior).abs().max() < 0.1  # trained, from the prior
    second = train(with_prior, tmp_path / "b", 5, [], max_steps=1, progress=False, real=frames, resume=first.checkpoint)
    assert second.steps == 3 and second.losses[:2] == first.losses  # its optimizer state carried on
    with pytest.raises(ValueError, match="label_prior"):
        train(cfg, tmp_path / "c", 5, [], max_steps=1, progress=False, real=frames, resume=start, label_prior=prior)


@pytest.mark.parametrize(
    "extra,says",
    [
        ([], "--label-prior needs a drive's labels"),
        (["--label-prior-threshold", "1.5"], "--label-prior-threshold must be in (0, 1), got 1.5"),
    ],
)
def test_a_label_prior_without_labels_or_with_a_threshold_out_of_range_is_one_line(extra, says, tmp_path, capfd):
    from occvo_cli.cli import main

    code = main(["train-occ", "--minutes", "1", "--out", str(tmp_path / "t"), "--seeds", "0", "--label-prior", "1"]
                + extra)  # fmt: skip
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and says in err[0], err
    assert not (tmp_path / "t" / "checkpoint.pt").exists()
