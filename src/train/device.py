"""Device choice and deterministic seeding shared by training, evaluation and benchmarks."""

from __future__ import annotations

import random

import torch

from src.errors import ConfigError


def pick_device(name: str) -> torch.device:
    """`auto`: CUDA when a GPU is visible, else CPU; `cpu` / `cuda` force one (cuda without a GPU is an
    error rather than a silent CPU fallback, so a paper-profile job never crawls on a CPU unnoticed)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("device: 'cuda' requested but torch sees no CUDA device")
    if name not in ("cpu", "cuda"):
        raise ConfigError(f"device: unknown device '{name}'; expected auto, cpu or cuda")
    return torch.device(name)


def precision(amp: bool, device: torch.device) -> str:
    """What arithmetic training runs in: `bf16-autocast` when `amp` is on and the device is CUDA (the only
    place autocast is used), else `fp32` (the papers' precision)."""
    return "bf16-autocast" if amp and device.type == "cuda" else "fp32"


def autocast_dtype(amp: bool, device: torch.device) -> torch.dtype | None:
    """The autocast dtype of training (`precision`): bfloat16 (no loss scaling needed) or None (fp32)."""
    return torch.bfloat16 if precision(amp, device) == "bf16-autocast" else None


def autocast(device_type: str, dtype: torch.dtype | None):
    """`torch.autocast` to `dtype` on `device_type`, or a disabled one (fp32) when `dtype` is None."""
    return torch.autocast(device_type=device_type, dtype=dtype, enabled=dtype is not None)


def seed_everything(seed: int) -> None:
    """Seed Python and torch, and ask cuDNN for deterministic kernels (same config + seed on the same
    machine -> same numbers). numpy randomness in this harness uses explicitly seeded Generators."""
    random.seed(seed)
    torch.manual_seed(seed)
    torch.backends.cudnn.benchmark = False
    torch.backends.cudnn.deterministic = True
