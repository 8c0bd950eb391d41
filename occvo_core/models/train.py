"""Training and evaluation of TPV-Former: synthetic scenes (images rendered from each frame's true occupancy) mixed
with a real drive's keyframes (DriveFrames: LiDAR labels and projected LiDAR depth)."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from occvo_core.cameras import nuscenes_rig
from occvo_core.grid import NUM_CLASSES
from occvo_core.models.losses import ImageAuxHead, class_weights, depth_loss, lovasz_softmax, occupancy_loss  # noqa: F401
from occvo_core.models.metrics import OccMetrics
from occvo_core.models.tpvformer import TPVFormer, TPVFormerConfig, autocast, load_checkpoint, save_checkpoint
from occvo_core.models.tpvformer.checkpoint import read_checkpoint
from occvo_core.models.training_data import Sample, SyntheticOccDataset, make_sample


@dataclass
class TrainResult:
    checkpoint: Path
    steps: int
    losses: list[float] = field(default_factory=list)
    seconds: float = 0.0


def train(
    cfg: TPVFormerConfig,
    out_dir: str | Path,
    minutes: float,
    seeds: list[int],
    frames: int = 20,
    stride: int = 2,
    lr: float = 2e-3,
    max_steps: int | None = None,
    seed: int = 0,
    progress: bool = True,
    dataset=None,
    preset_name: str = "",
    warmup: int = 30,
    cache_dir: str | Path | None = None,
    aux_weight: float = 0.5,
    depth_weight: float = 1.0,
    depth_only: bool = False,
    resume: str | Path | None = None,
    real=None,
    real_fraction: float = 0.5,
    device: str | torch.device = "cpu",
    meta: dict | None = None,
    label_prior: torch.Tensor | None = None,
) -> TrainResult:
    """Time-budgeted AdamW with warm-up and cosine decay over the budget; writes checkpoint.pt, loss_curve.png, train_log.json
    and checkpoint.state.pt (optimizer, step, losses: what `resume` continues from).

    `resume`: a checkpoint of the same config to continue from. With its .state.pt beside it the optimizer, the aux head,
    the step count and the loss history carry on; the learning rate restarts its cosine over the new budget (SGDR).
    `real`: a drive's DriveFrames; a step takes one of its keyframes (augmented) with probability `real_fraction`
    (1 without seeds), its voxel loss inside mask_camera only, its image losses at LiDAR returns only; the free-class
    offset is then calibrated on its keyframes as recorded. `device`: cuda trains in bf16 autocast. `depth_weight`
    scales the depth head's loss inside the image losses (their weight: `aux_weight`). `depth_only`: the image
    branch alone (backbone, depth head, pixel classes; no TPV encoder or voxels), at a small part of a step's cost.
    `label_prior`: the initial free-logit offset of a `cfg.label_prior` model (label_prior.free_prior); a resumed
    checkpoint without one gets it added (with a fresh optimizer).
    """
    device = torch.device(device)
    if real is not None and not seeds:
        real_fraction = 1.0
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    state = _resume_state(resume)
    start_step = state.get("step", 0)
    torch.manual_seed(seed + start_step)
    rng = np.random.default_rng([seed, start_step])  # a resumed run does not replay the first run's frame order
    rig = nuscenes_rig(*cfg.input_size)
    data = (
        dataset
        if dataset is not None or not seeds
        else SyntheticOccDataset(seeds, frames, rig, stride=stride, cache_dir=cache_dir)
    )
    model = TPVFormer(cfg).train()
    if resume is not None:  # shapes checked against cfg; the calibrated free-logit offset is re-fitted at the end
        adds_prior = label_prior is not None and not read_checkpoint(resume)["config"].get("label_prior")
        base = cfg.model_copy(update={"label_prior": False}) if adds_prior else cfg
        model.load_state_dict(load_checkpoint(resume, config=base).state_dict(), strict=not adds_prior)
        if adds_prior:
            state.pop("optimizer", None)  # its parameter list has no prior
        model.cfg = cfg.model_copy(update={"free_logit_bias": 0.0})
        model.train()
    if label_prior is not None:
        if not cfg.label_prior:
            raise ValueError("label_prior given for a config without one (TPVFormerConfig.label_prior)")
        model.free_prior.data.copy_(label_prior)
    model.to(device)
    # Class frequencies inside the camera mask from a few frames of each source.
    counts = np.zeros(NUM_CLASSES)
    firsts = []
    for src in (data, real):
        if src is None:
            continue
        for k in rng.choice(len(src), size=min(8, len(src)), replace=False):
            s = src[int(k)] if src is data else src.sample(int(k))
            counts += np.bincount(s.semantics[s.camera_mask], minlength=NUM_CLASSES)
            firsts.append(s)
    weights = class_weights(counts + 1).to(device)
    params = list(model.parameters())
    aux_head, captured, hooks = None, {}, []
    if aux_weight > 0 and getattr(firsts[0], "depth", None) is not None:  # image supervision: renderer or LiDAR
        aux_head = ImageAuxHead(cfg.backbone.fpn_channels).to(device).train()
        params += list(aux_head.parameters())
        hooks.append(model.backbone.register_forward_hook(lambda _m, _i, out: captured.__setitem__("levels", out)))
        if model.depth_head is not None:
            hooks.append(model.depth_head.register_forward_hook(lambda _m, _i, out: captured.__setitem__("depth", out)))
    if depth_only and (aux_head is None or model.depth_head is None):
        raise ValueError("depth_only needs a depth head and depth targets (a drive's LiDAR or rendered frames)")
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=0.01)
    if "optimizer" in state:
        opt.load_state_dict(state["optimizer"])
        if aux_head is not None and "aux_head" in state:
            aux_head.load_state_dict(state["aux_head"])
        warmup = 1  # the optimizer's moments are warm already
    budget = minutes * 60.0
    start, losses, step = time.monotonic(), list(state.get("losses", [])), start_step
    seconds_before = float(state.get("seconds", 0.0))
    bar = tqdm(
        total=int(budget),
        unit="s",
        disable=not progress,
        desc="train-occ",
        bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt}s [{postfix}]",
    )
    order = rng.permutation(len(data)) if data is not None else np.zeros(1, np.int64)
    taken = 0  # synthetic frames taken: the order's position
    last_save = start
    ckpt = out / "checkpoint.pt"
    while True:
        elapsed = time.monotonic() - start
        if elapsed >= budget or (max_steps is not None and step - start_step >= max_steps):
            break
        frac = elapsed / budget
        for g in opt.param_groups:
            g["lr"] = (
                lr * min(1.0, (step - start_step + 1) / warmup) * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * frac)))
            )
        if real is not None and (data is None or rng.random() < real_fraction):
            s = real.sample(int(rng.integers(len(real))), rng)
        else:
            s = data[int(order[taken % len(order)])]
            taken += 1
            if taken % len(order) == 0:
                order = rng.permutation(len(data))
        with autocast(device):
            if depth_only:
                model.image_depth(s.images[None].to(device))  # the hooks below capture what the losses need
                loss, parts = torch.zeros((), device=device), {"ce": 0.0, "lovasz": 0.0}
            else:
                logits = model(s.images[None].to(device), s.intrinsics[None].to(device), s.cam_to_ego[None].to(device))
                loss, parts = occupancy_loss(
                    logits,
                    torch.from_numpy(s.semantics[None]).long().to(device),
                    torch.from_numpy(s.camera_mask[None]).to(device),
                    weights,
                    outside_weight=0.0 if s.sparse else 0.1,  # a real frame knows nothing outside mask_camera
                )
            if aux_head is not None:
                aux = aux_head.loss(captured.pop("levels")[0], s.pixel_labels, sparse=s.sparse)
                if "depth" in captured:
                    depth = depth_loss(captured.pop("depth"), s.depth, s.intrinsics, cfg.depth_range)
                    aux = aux + depth_weight * depth
                    parts["depth"] = float(depth.detach())
                loss = loss + aux_weight * aux
                parts["aux"] = float(aux.detach())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 5.0)
        opt.step()
        losses.append(float(loss.detach()))
        step += 1
        bar.n = min(int(time.monotonic() - start), int(budget))
        bar.set_postfix_str(
            f"step {step} loss {np.mean(losses[-20:]):.3f} ce {parts['ce']:.3f} lovasz {parts['lovasz']:.3f}"
            + (f" aux {parts['aux']:.3f}" if "aux" in parts else "")
            + (f" depth {parts['depth']:.3f}" if "depth" in parts else "")
        )
        bar.refresh()
        if time.monotonic() - last_save > 120:
            _save(
                ckpt,
                model,
                losses,
                step,
                seconds_before + time.monotonic() - start,
                seeds,
                preset_name,
                opt,
                aux_head,
                meta,
            )
            last_save = time.monotonic()
    bar.close()
    seconds = seconds_before + time.monotonic() - start
    for hook in hooks:
        hook.remove()
    if real is not None:  # served on real cameras: the offset that fits them
        calibration = calibrate_free_bias(model, (real.sample(k) for k in range(len(real))), device=device)
    elif dataset is None and stride > 1 and frames > 1:  # frames of the training scenes that training did not use
        held = SyntheticOccDataset(seeds[:12], frames, rig, stride=frames, cache_dir=cache_dir, first=1)
        calibration = calibrate_free_bias(model, (held[k] for k in range(len(held))), device=device)
    else:
        calibration = calibrate_free_bias(model, [data[int(k)] for k in order[:6]], device=device)
    model.meta_calibration = calibration
    _save(ckpt, model, losses, step, seconds, seeds, preset_name, opt, aux_head, meta)
    plot_losses(losses, out / "loss_curve.png")
    (out / "train_log.json").write_text(
        json.dumps(
            {
                "steps": step,
                "seconds": seconds,
                "losses": losses,
                "seeds": list(seeds),
                "preset": preset_name,
                "config": cfg.model_dump(mode="json"),
                **(meta or {}),
            },
            indent=1,
        )
    )
    return TrainResult(ckpt, step, losses, seconds)


@torch.no_grad()
def calibrate_free_bias(
    model: TPVFormer, samples, candidates=tuple(np.arange(-3.0, 5.01, 0.25)), device: torch.device = torch.device("cpu")
) -> dict:
    """Pick the free-class logit offset maximising mIoU + geometry IoU on `samples` (not evaluation seeds); sets it
    on the model. Negative offsets too: a model fine-tuned on sparse real labels can come out short of occupied."""
    model.eval()
    cfg = model.cfg.model_copy(update={"free_logit_bias": 0.0})
    model.cfg = cfg
    metrics = {float(b): OccMetrics() for b in candidates}
    for s in samples:  # one frame's logits at a time: 18 x 640k floats each
        with autocast(device):
            lg = model(s.images[None].to(device), s.intrinsics[None].to(device), s.cam_to_ego[None].to(device))
        lg = lg[0].permute(1, 2, 3, 0).float().cpu()
        mask = s.camera_mask
        other, cls = lg[..., :-1].max(-1)  # the best occupied class: the offset only decides it against free
        margin, cls = (lg[..., -1] - other).numpy()[mask], cls.numpy()[mask]
        for bias, m in metrics.items():
            m.update(np.where(margin + bias >= 0, lg.shape[-1] - 1, cls), s.semantics[mask])
    table = {b: {"miou": m.miou(), "geometry_iou": m.geometry_iou()} for b, m in metrics.items()}
    best = max(table, key=lambda b: table[b]["miou"] + table[b]["geometry_iou"])
    model.cfg = cfg.model_copy(update={"free_logit_bias": float(best)})
    return {"free_logit_bias": float(best), "table": {str(k): v for k, v in table.items()}}


def _resume_state(resume: str | Path | None) -> dict:
    """What a resumed run continues from: the .state.pt beside the checkpoint, else the step count and seconds of
    the checkpoint's meta (weights only: a fresh optimizer)."""
    if resume is None:
        return {}
    meta = read_checkpoint(resume).get("meta", {})  # one clear error for a missing or foreign file
    path = Path(resume).with_suffix(".state.pt")
    if path.is_file():
        return torch.load(path, map_location="cpu", weights_only=True)
    return {"step": int(meta.get("steps") or 0), "seconds": float(meta.get("seconds") or 0.0)}  # weights only


def _save(path, model, losses, step, seconds, seeds, preset_name, opt=None, aux_head=None, meta=None):
    model.eval()
    if opt is not None:  # beside the checkpoint, so that the checkpoint itself stays small enough to ship
        state = {"optimizer": opt.state_dict(), "step": step, "seconds": seconds, "losses": list(losses)}
        if aux_head is not None:
            state["aux_head"] = aux_head.state_dict()
        tmp = path.with_suffix(".state.pt.tmp")
        torch.save(state, tmp)
        tmp.replace(path.with_suffix(".state.pt"))
    save_checkpoint(
        path,
        model,
        {
            "steps": step,
            "seconds": seconds,
            "final_loss": float(np.mean(losses[-20:])) if losses else None,
            "train_seeds": list(seeds),
            "preset": preset_name,
            "calibration": getattr(model, "meta_calibration", None),
            **(meta or {}),
        },
    )
    model.train()


def plot_losses(losses: list[float], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(losses, lw=0.6, alpha=0.4, label="step")
    if len(losses) >= 20:
        ax.plot(
            np.arange(19, len(losses)), np.convolve(losses, np.ones(20) / 20, mode="valid"), lw=1.5, label="mean of 20"
        )
    ax.set_xlabel("step")
    ax.set_ylabel("cross entropy + Lovasz-softmax")
    ax.set_title("TPV-Former training loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


@torch.no_grad()
def predict_labels(model: TPVFormer, sample: Sample, device: torch.device = torch.device("cpu")) -> np.ndarray:
    with autocast(device):
        logits = model(
            sample.images[None].to(device), sample.intrinsics[None].to(device), sample.cam_to_ego[None].to(device)
        )
    return logits[0].argmax(0).to(torch.uint8).cpu().numpy()


def evaluate(
    model: TPVFormer,
    seeds: list[int],
    frames: int = 20,
    stride: int = 5,
    progress: bool = True,
    device: torch.device = torch.device("cpu"),
) -> OccMetrics:
    """Occ3D-style metrics over frames 0, stride, ... of each held-out seed, inside the renderer's camera mask."""
    model.eval().to(device)
    data = SyntheticOccDataset(seeds, frames, nuscenes_rig(*model.cfg.input_size), stride=stride)
    metrics = OccMetrics()
    for k in tqdm(range(len(data)), desc="eval-occ", disable=not progress):
        s = data[k]
        metrics.update(predict_labels(model, s, device), s.semantics, s.camera_mask)
    return metrics


__all__ = [
    "SyntheticOccDataset",
    "make_sample",
    "lovasz_softmax",
    "occupancy_loss",
    "train",
    "evaluate",
    "predict_labels",
    "plot_losses",
]
