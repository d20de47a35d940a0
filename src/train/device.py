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


#: What `precision` says of fp32 on a GPU whose convolutions PyTorch runs in TF32 (cuDNN's default on
#: compute capability 8.0 and newer: `torch.backends.cudnn.allow_tf32`).
FP32_TF32_CONV = "fp32 (TF32 convolutions)"


def precision(amp: bool, device: torch.device) -> str:
    """What arithmetic training runs in: `bf16-autocast` when `amp` is on and the device is CUDA (the only
    place autocast is used); else `fp32` (the papers' precision), stated as `FP32_TF32_CONV` where PyTorch
    runs the convolutions in TF32 (a CUDA GPU of compute capability >= 8.0 with cuDNN's TF32 allowed, its
    default), and with ` TF32 matmuls` added where `torch.backends.cuda.matmul.allow_tf32` is on too."""
    if amp and device.type == "cuda":
        return "bf16-autocast"
    if device.type != "cuda" or not torch.cuda.is_available():
        return "fp32"
    if torch.cuda.get_device_capability(device)[0] < 8:
        return "fp32"
    conv, matmul = tf32_flags()
    if not (conv or matmul):
        return "fp32"
    parts = [name for name, on in (("convolutions", conv), ("matmuls", matmul)) if on]
    return f"fp32 (TF32 {' and '.join(parts)})"


def tf32_flags() -> tuple[bool, bool]:
    """Whether PyTorch may run (convolutions, matmuls) in TF32 on an Ampere or newer GPU."""
    return bool(torch.backends.cudnn.allow_tf32), bool(torch.backends.cuda.matmul.allow_tf32)


def cpu_model(cpuinfo: str = "/proc/cpuinfo") -> str:
    """The CPU's model name (`model name` of /proc/cpuinfo, else the platform's processor string), never
    blank: `unknown CPU` when neither names it."""
    import platform
    from pathlib import Path

    try:
        for line in Path(cpuinfo).read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and value.strip():
                return value.strip()
    except OSError:
        pass
    return platform.processor().strip() or "unknown CPU"


def device_card(device: torch.device) -> dict[str, str]:
    """What a timing or a run was measured on: the device's name (the GPU's, or the CPU's model) and the
    CPU threads torch uses (host work, and the whole computation on a CPU)."""
    name = torch.cuda.get_device_name(device) if device.type == "cuda" else cpu_model()
    return {"device_name": name, "threads": str(torch.get_num_threads())}


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
