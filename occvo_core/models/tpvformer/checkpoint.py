"""Checkpoints carry the config they belong to; weights that do not fit a config are a typed error."""

from __future__ import annotations

from pathlib import Path

import torch

from occvo_core.errors import OccVOError
from occvo_core.models.tpvformer.config import TPVFormerConfig
from occvo_core.models.tpvformer.model import TPVFormer

FORMAT = "occvo-tpvformer/1"


class CheckpointError(OccVOError, OSError):
    """A checkpoint file that cannot be read as a TPV-Former checkpoint."""

    def __init__(self, path: object, reason: str):
        self.path, self.reason = path, reason
        super().__init__(f"{path}: {reason}")


class CheckpointMismatchError(CheckpointError, ValueError):
    """Weights whose tensors do not match the model built from the requested config."""

    def __init__(
        self, path: object, mismatched: list[tuple[str, tuple, tuple]], missing: list[str], unexpected: list[str]
    ):
        self.mismatched, self.missing, self.unexpected = mismatched, missing, unexpected
        parts = [f"{n}: checkpoint {tuple(a)} vs model {tuple(b)}" for n, a, b in mismatched[:8]]
        if len(mismatched) > 8:
            parts.append(f"... {len(mismatched) - 8} more")
        if missing:
            parts.append(f"missing {missing[:5]}{' ...' if len(missing) > 5 else ''}")
        if unexpected:
            parts.append(f"unexpected {unexpected[:5]}{' ...' if len(unexpected) > 5 else ''}")
        super().__init__(path, "weights do not match the config: " + "; ".join(parts))


def save_checkpoint(path: str | Path, model: TPVFormer, meta: dict | None = None) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {
        "format": FORMAT,
        "config": model.cfg.model_dump(mode="json"),
        "state_dict": model.state_dict(),
        "meta": meta or {},
    }
    tmp = path.with_suffix(path.suffix + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)  # never leave a half-written checkpoint under the real name
    return path


def read_checkpoint(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, "no such file")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unreadable file is one typed error
        raise CheckpointError(path, f"not a torch checkpoint ({type(exc).__name__}: {exc})") from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(path, f"not an {FORMAT} checkpoint")
    return payload


def load_checkpoint(
    path: str | Path, config: TPVFormerConfig | None = None, device: str | torch.device = "cpu"
) -> TPVFormer:
    """Model with the checkpoint's weights, built from its own config or from `config` (whose shapes must match)."""
    payload = read_checkpoint(path)
    try:
        cfg = config or TPVFormerConfig.model_validate(payload["config"])
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(path, f"invalid config in checkpoint: {exc}") from None
    model = TPVFormer(cfg)
    own, theirs = model.state_dict(), payload["state_dict"]
    mismatched = [
        (k, tuple(v.shape), tuple(own[k].shape)) for k, v in theirs.items() if k in own and v.shape != own[k].shape
    ]
    missing = [k for k in own if k not in theirs]
    unexpected = [k for k in theirs if k not in own]
    if mismatched or missing or unexpected:
        raise CheckpointMismatchError(path, mismatched, missing, unexpected)
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in theirs.items()})  # fp16 files too
    model.meta = payload.get("meta", {})
    return model.to(device).eval()


def save_half(
    src: str | Path, dst: str | Path, free_logit_bias: float | None = None, lift_range: float | None = None
) -> Path:
    """src's checkpoint with its floating-point weights in fp16 (half the bytes; load_checkpoint gives fp32 back);
    `free_logit_bias` replaces the offset its training calibrated, `lift_range` sets depth lifting (each chosen on
    held-out frames)."""
    payload = read_checkpoint(src)
    for name, value in (("free_logit_bias", free_logit_bias), ("lift_range", lift_range)):
        if value is not None:
            payload["config"] = {**payload["config"], name: float(value)}
            payload["meta"] = {**payload.get("meta", {}), f"{name}_chosen": float(value)}
    TPVFormerConfig.model_validate(payload["config"])  # a bad choice fails here, not when the file is served
    payload["state_dict"] = {k: v.half() if v.is_floating_point() else v for k, v in payload["state_dict"].items()}
    dst = Path(dst)
    dst.parent.mkdir(parents=True, exist_ok=True)
    tmp = dst.with_suffix(dst.suffix + ".tmp")
    torch.save(payload, tmp)
    tmp.replace(dst)
    return dst


# The confidences the shipped model is served with (min_confidence, min_ground_confidence), chosen on seeds
# 2000-2004: its predicted ground agrees with less motion than the truth, so none of it is used (docs/model.md).
SHIPPED_THRESHOLDS = (0.9, 1.0)

# The shipped model for real camera rigs (a nuScenes drive): `tiny` fine-tuned on scene-0916's keyframes with their
# LiDAR labels (docs/model.md); `tiny` stays the synthetic town's.
REAL_RIG_MODEL = "tiny_nuscenes0916"
SERVED_THRESHOLDS = {"tiny": SHIPPED_THRESHOLDS, REAL_RIG_MODEL: (0.0, 0.0)}


def served_model(real_rig: bool) -> tuple[Path, tuple[float, float]]:
    """The shipped checkpoint and its thresholds for a real camera rig (a recorded drive) or the synthetic town."""
    name = REAL_RIG_MODEL if real_rig else "tiny"
    return shipped_checkpoint(name), SERVED_THRESHOLDS[name]


def shipped_checkpoint(name: str = "tiny") -> Path:
    """The trained checkpoint that ships as package data (docs/model.md: its recipe and its scores)."""
    from importlib.resources import files

    res = files("occvo_core.models.tpvformer").joinpath("weights", f"{name}.pt")
    if not res.is_file():
        raise CheckpointError(
            res, f"no shipped '{name}' checkpoint in the package (installed without its package data?)"
        )
    return Path(str(res))  # setuptools installs package data as plain files
