"""Device selection: cuda when present (bf16 autocast), cpu otherwise (fp32)."""

from __future__ import annotations

import contextlib

import torch


def select_device(name: str | None = None) -> torch.device:
    """`name` ("cpu", "cuda", "cuda:1") when given, else cuda if available, else cpu."""
    if name:
        device = torch.device(name)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise RuntimeError(f"device {name!r} requested but torch sees no CUDA device")
        return device
    return torch.device("cuda" if torch.cuda.is_available() else "cpu")


def autocast(device: torch.device):
    """bf16 autocast on cuda; nothing on cpu (bf16 matmuls there are slower than fp32 on most CPUs)."""
    if device.type == "cuda":
        return torch.autocast("cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()
