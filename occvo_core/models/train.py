"""Training and evaluation of TPV-Former on synthetic scenes: images rendered from each frame's true occupancy."""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from tqdm import tqdm

from occvo_core.cameras import CameraRig, RenderStyle, nuscenes_rig, render
from occvo_core.grid import NUM_CLASSES
from occvo_core.models.metrics import OccMetrics
from occvo_core.models.tpvformer import TPVFormer, TPVFormerConfig, autocast, save_checkpoint

@dataclass
class Sample:
    images: torch.Tensor  # (6, 3, H, W) float in [0, 1]
    intrinsics: torch.Tensor  # (6, 3, 3)
    cam_to_ego: torch.Tensor  # (6, 4, 4)
    semantics: np.ndarray  # (200, 200, 16) uint8
    camera_mask: np.ndarray  # (200, 200, 16) bool


def make_sample(semantics: np.ndarray, rig: CameraRig, rng: int | np.random.Generator = 0, style: RenderStyle = RenderStyle()) -> Sample:
    frame = render(semantics, rig, style, rng)
    images = torch.from_numpy(frame.images).permute(0, 3, 1, 2).float().div_(255.0)
    return Sample(images, torch.tensor(rig.intrinsics, dtype=torch.float32), torch.tensor(rig.cam_to_ego, dtype=torch.float32),
                  np.asarray(semantics, np.uint8), frame.camera_mask)


class SyntheticOccDataset:
    """Frames of SyntheticScene(seed) for each seed; each rendered once on first use and kept (small at tiny sizes)."""

    def __init__(self, seeds: list[int], frames: int, rig: CameraRig, stride: int = 1):
        from occvo_core.sim import SyntheticScene  # the sim is only needed for synthetic training/eval

        self.seeds, self.rig = list(seeds), rig
        self._scene_cls, self._frames, self._stride = SyntheticScene, frames, stride
        self._scenes: dict[int, object] = {}
        self.index = [(s, i) for s in self.seeds for i in range(0, frames, stride)]
        self._cache: dict[int, Sample] = {}

    def __len__(self) -> int:
        return len(self.index)

    def __getitem__(self, k: int) -> Sample:
        if k not in self._cache:
            seed, i = self.index[k]
            if seed not in self._scenes:
                self._scenes[seed] = self._scene_cls(seed=seed, frames=self._frames)
            self._cache[k] = make_sample(self._scenes[seed].true_grid(i), self.rig, rng=seed * 1000 + i)
        return self._cache[k]


# -- losses ---------------------------------------------------------------------------------------------------------

def _lovasz_grad(gt_sorted: torch.Tensor) -> torch.Tensor:
    gts = gt_sorted.sum()
    intersection = gts - gt_sorted.cumsum(0)
    union = gts + (1 - gt_sorted).cumsum(0)
    jaccard = 1.0 - intersection / union
    jaccard[1:] = jaccard[1:] - jaccard[:-1]
    return jaccard


def lovasz_softmax(probs: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """Lovasz-softmax (Berman et al., CVPR 2018) over the classes present: probs (P, C), labels (P,)."""
    losses = []
    for c in labels.unique():
        fg = (labels == c).float()
        errors = (fg - probs[:, c]).abs()
        errors_sorted, perm = torch.sort(errors, descending=True)
        losses.append(torch.dot(errors_sorted, _lovasz_grad(fg[perm])))
    return torch.stack(losses).mean() if losses else probs.sum() * 0


def class_weights(frequencies: np.ndarray) -> torch.Tensor:
    """Inverse log frequency: rare classes weigh up to ~10x free space."""
    f = np.asarray(frequencies, np.float64) / max(1, np.sum(frequencies))
    return torch.tensor(1.0 / np.log(1.1 + f), dtype=torch.float32)


def occupancy_loss(logits: torch.Tensor, semantics: torch.Tensor, mask: torch.Tensor, weights: torch.Tensor,
                   outside_weight: float = 0.1, lovasz_voxels: int = 32768, generator: torch.Generator | None = None
                   ) -> tuple[torch.Tensor, dict]:
    """Weighted cross entropy on camera-visible voxels (plus the rest at `outside_weight`) + Lovasz-softmax on a random
    subset of the visible voxels (the sort over every voxel would dominate a CPU step).

    logits (B, C, X, Y, Z), semantics (B, X, Y, Z) long, mask (B, X, Y, Z) bool.
    """
    ce = F.cross_entropy(logits, semantics, weight=weights, reduction="none")
    w = torch.where(mask, 1.0, outside_weight)
    ce = (ce * w).sum() / w.sum()
    flat, labels = logits.permute(0, 2, 3, 4, 1)[mask], semantics[mask]
    if len(labels) > lovasz_voxels:
        keep = torch.randperm(len(labels), generator=generator)[:lovasz_voxels]
        flat, labels = flat[keep], labels[keep]
    lovasz = lovasz_softmax(flat.float().softmax(-1), labels)
    return ce + lovasz, {"ce": float(ce.detach()), "lovasz": float(lovasz.detach())}


# -- training -------------------------------------------------------------------------------------------------------

@dataclass
class TrainResult:
    checkpoint: Path
    steps: int
    losses: list[float] = field(default_factory=list)
    seconds: float = 0.0


def train(cfg: TPVFormerConfig, out_dir: str | Path, minutes: float, seeds: list[int], frames: int = 20, stride: int = 2, lr: float = 2e-3,
          max_steps: int | None = None, seed: int = 0, progress: bool = True, dataset=None, preset_name: str = "",
          warmup: int = 30) -> TrainResult:
    """Time-budgeted AdamW with warm-up and cosine decay over the budget; writes checkpoint.pt, loss_curve.png, train_log.json."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    rig = nuscenes_rig(*cfg.input_size)
    data = dataset if dataset is not None else SyntheticOccDataset(seeds, frames, rig, stride=stride)
    model = TPVFormer(cfg).train()
    # Class frequencies inside the camera mask from a few frames.
    counts = np.zeros(NUM_CLASSES)
    for k in rng.choice(len(data), size=min(8, len(data)), replace=False):
        s = data[int(k)]
        counts += np.bincount(s.semantics[s.camera_mask], minlength=NUM_CLASSES)
    weights = class_weights(counts + 1)
    opt = torch.optim.AdamW(model.parameters(), lr=lr, weight_decay=0.01)
    budget = minutes * 60.0
    start, losses, step = time.monotonic(), [], 0
    bar = tqdm(total=int(budget), unit="s", disable=not progress, desc="train-occ",
               bar_format="{l_bar}{bar}| {n_fmt}/{total_fmt}s [{postfix}]")
    order = rng.permutation(len(data))
    last_save = start
    ckpt = out / "checkpoint.pt"
    while True:
        elapsed = time.monotonic() - start
        if elapsed >= budget or (max_steps is not None and step >= max_steps):
            break
        frac = elapsed / budget
        for g in opt.param_groups:
            g["lr"] = lr * min(1.0, (step + 1) / warmup) * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * frac)))
        s = data[int(order[step % len(order)])]
        if step % len(order) == len(order) - 1:
            order = rng.permutation(len(data))
        logits = model(s.images[None], s.intrinsics[None], s.cam_to_ego[None])
        loss, parts = occupancy_loss(logits, torch.from_numpy(s.semantics[None]).long(), torch.from_numpy(s.camera_mask[None]), weights)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        losses.append(float(loss.detach()))
        step += 1
        bar.n = min(int(time.monotonic() - start), int(budget))
        bar.set_postfix_str(f"step {step} loss {np.mean(losses[-20:]):.3f} ce {parts['ce']:.3f} lovasz {parts['lovasz']:.3f}")
        bar.refresh()
        if time.monotonic() - last_save > 120:
            _save(ckpt, model, losses, step, time.monotonic() - start, seeds, preset_name)
            last_save = time.monotonic()
    bar.close()
    seconds = time.monotonic() - start
    calibration = calibrate_free_bias(model, [data[int(k)] for k in order[:6]])
    model.meta_calibration = calibration
    _save(ckpt, model, losses, step, seconds, seeds, preset_name)
    plot_losses(losses, out / "loss_curve.png")
    (out / "train_log.json").write_text(json.dumps({"steps": step, "seconds": seconds, "losses": losses, "seeds": list(seeds),
                                                    "preset": preset_name, "config": cfg.model_dump(mode="json")}, indent=1))
    return TrainResult(ckpt, step, losses, seconds)


@torch.no_grad()
def calibrate_free_bias(model: TPVFormer, samples: list[Sample], candidates=(0.0, 0.5, 1.0, 1.5, 2.0, 3.0, 4.0)) -> dict:
    """Pick the free-class logit offset maximising mIoU + geometry IoU on (training) samples; sets it on the model."""
    model.eval()
    cfg = model.cfg.model_copy(update={"free_logit_bias": 0.0})
    model.cfg = cfg
    logits = [model(s.images[None], s.intrinsics[None], s.cam_to_ego[None])[0].permute(1, 2, 3, 0) for s in samples]
    table = {}
    for bias in candidates:
        m = OccMetrics()
        for s, lg in zip(samples, logits):
            adjusted = lg.clone()
            adjusted[..., -1] += bias
            m.update(adjusted.argmax(-1).numpy(), s.semantics, s.camera_mask)
        table[bias] = {"miou": m.miou(), "geometry_iou": m.geometry_iou()}
    best = max(candidates, key=lambda b: table[b]["miou"] + table[b]["geometry_iou"])
    model.cfg = cfg.model_copy(update={"free_logit_bias": float(best)})
    return {"free_logit_bias": float(best), "table": {str(k): v for k, v in table.items()}}


def _save(path, model, losses, step, seconds, seeds, preset_name):
    model.eval()
    save_checkpoint(path, model, {"steps": step, "seconds": seconds, "final_loss": float(np.mean(losses[-20:])) if losses else None,
                                  "train_seeds": list(seeds), "preset": preset_name,
                                  "calibration": getattr(model, "meta_calibration", None)})
    model.train()


def plot_losses(losses: list[float], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(losses, lw=0.6, alpha=0.4, label="step")
    if len(losses) >= 20:
        ax.plot(np.arange(19, len(losses)), np.convolve(losses, np.ones(20) / 20, mode="valid"), lw=1.5, label="mean of 20")
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
        logits = model(sample.images[None].to(device), sample.intrinsics[None].to(device), sample.cam_to_ego[None].to(device))
    return logits[0].argmax(0).to(torch.uint8).cpu().numpy()


def evaluate(model: TPVFormer, seeds: list[int], frames: int = 20, stride: int = 5, progress: bool = True,
             device: torch.device = torch.device("cpu")) -> OccMetrics:
    """Occ3D-style metrics over frames 0, stride, ... of each held-out seed, inside the renderer's camera mask."""
    model.eval().to(device)
    data = SyntheticOccDataset(seeds, frames, nuscenes_rig(*model.cfg.input_size), stride=stride)
    metrics = OccMetrics()
    for k in tqdm(range(len(data)), desc="eval-occ", disable=not progress):
        s = data[k]
        metrics.update(predict_labels(model, s, device), s.semantics, s.camera_mask)
    return metrics


__all__ = ["SyntheticOccDataset", "make_sample", "lovasz_softmax", "occupancy_loss", "train", "evaluate", "predict_labels",
           "plot_losses"]
