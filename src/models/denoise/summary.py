"""Model size and cost: parameter counts, FLOPs per pixel, and the text of `stage=summary`.

FLOPs are counted as 2 x multiply-accumulates (MACs). Convolution MACs are measured, not derived from the
config: forward hooks on every `nn.Conv2d` record out_channels * (in_channels / groups) * kh * kw MACs per
output pixel during one forward pass on a small random batch (bias additions and ReLUs are not counted,
the usual convention). The rest is what each denoiser declares (`Denoiser.kernel_flops_per_pixel()`,
`src/models/denoise/base.py`): the kernel application (Bako et al. 2017, Eq. 5-6; k*k*3 MACs per branch
per pixel plus ~3*k*k FLOPs for the softmax, `kernels.kernel_application_flops`) of each branch, or the
U-Net KPCN's kernels at every scale weighted by the scale's pixel fraction plus the composition.

A denoiser is probed with a `random_batch` of the branches it reads (`Denoiser.branches`); scale
compositors' convolutions (`compositor_modules()`) are counted by the hooks and also shown on their own.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch
from torch import nn

from src.data.features import PAPER_CHANNELS
from src.data.sequence_dataset import RADIANCE_BRANCH
from src.data.shards import SHARD_CHANNELS
from src.models.denoise.base import Denoiser
from src.models.denoise.models import BRANCHES, BranchDenoiser
from src.models.parameters import count_parameters

#: Side of the random batch the FLOP count runs on: 'same' convolutions cost the same per pixel at any
#: size, so a tiny frame gives exact per-pixel counts cheaply.
PROBE_SIZE = 8


def random_batch(
    height: int,
    width: int,
    *,
    in_channels: int = len(PAPER_CHANNELS),
    branches: Sequence[str] = BRANCHES,
    batch_size: int = 1,
    generator: torch.Generator | None = None,
    device: torch.device | str | None = None,
) -> dict[str, torch.Tensor]:
    """A random batch with every key of the `base.py` contract for `branches` (the still images' two by
    default; the sequences' `radiance` adds their colour parts and flow), in plausible ranges (colours
    >= 0, normals in [-1, 1], depth in [0, 1], motion in pixels); for benchmarks and FLOP counting, not
    for accuracy. Transformed keys are random values >= 0, valid under every transform."""

    def rand(channels: int, lo: float = 0.0, hi: float = 1.0) -> torch.Tensor:
        x = torch.rand((batch_size, channels, height, width), generator=generator)
        return (lo + (hi - lo) * x).to(device)

    if tuple(branches) == (RADIANCE_BRANCH,):
        batch = {key: rand(3) for key in SEQUENCE_RGB_KEYS}
        batch["normal"] = rand(3, -1.0, 1.0)
        batch[f"{RADIANCE_BRANCH}_in"] = rand(in_channels, -1.0, 1.0)
        batch["depth"] = rand(1)
        batch["motion"] = rand(2, -4.0, 4.0)
        return batch
    batch = {key: rand(len(names)) for key, names in SHARD_CHANNELS.items() if not key.endswith("_in")}
    for branch in branches:
        batch[f"{branch}_in"] = rand(in_channels, -1.0, 1.0)
        batch[f"{branch}_t"] = rand(3)
        if f"{branch}_target" not in batch:
            batch[f"{branch}_target"] = rand(3)
    batch["normal"] = rand(len(SHARD_CHANNELS["normal"]), -1.0, 1.0)
    return batch


#: The sequences' keys with 3 channels (`base.py`), all but the inputs and the flow.
SEQUENCE_RGB_KEYS = (
    f"{RADIANCE_BRANCH}_t",
    "surface_t",
    "volume_t",
    "color",
    "reference",
    f"{RADIANCE_BRANCH}_target",
    "target_surface",
    "target_volume",
    "albedo",
    "normal",
)


def _conv_macs(model: nn.Module, run) -> int:
    """Total conv MACs of one call of `run()`, counted by forward hooks on every Conv2d of `model`."""
    total = 0

    def hook(conv: nn.Conv2d, _inputs, output: torch.Tensor) -> None:
        nonlocal total
        n, c_out, h, w = output.shape
        kh, kw = conv.kernel_size
        total += n * h * w * c_out * (conv.in_channels // conv.groups) * kh * kw

    handles = [m.register_forward_hook(hook) for m in model.modules() if isinstance(m, nn.Conv2d)]
    try:
        with torch.inference_mode():
            run()
    finally:
        for handle in handles:
            handle.remove()
    return total


def _probe_size(model: nn.Module) -> int:
    """PROBE_SIZE, rounded up to the model's `size_multiple` (a U-Net pads its input to a multiple of
    2^(S-1): probing at such a size keeps the per-pixel counts exact)."""
    multiple = int(model.size_multiple) if isinstance(model, Denoiser) else 1
    return -(-max(PROBE_SIZE, multiple) // multiple) * multiple


def flops_per_pixel(model: nn.Module, in_channels: int = len(PAPER_CHANNELS)) -> dict[str, Any]:
    """FLOPs per output pixel: {"total", "conv", "kernel"} ("kernel": both branches of a two-branch model,
    or what a model's `kernel_flops_per_pixel()` reports), and for a U-Net KPCN "compositor": the
    part of "conv" in its scale compositors.

    A plain network (e.g. a `ConvStack`) is fed an (1, in_channels, s, s) tensor; a `Denoiser` a random
    batch of the branches it reads. A non-learned filter reports its own `flops_per_pixel()` as
    "total" if it defines one, else every entry is None (unknown).
    """
    if isinstance(model, Denoiser) and not model.learned:
        own = model.flops_per_pixel()
        return {"total": None if own is None else float(own), "conv": None, "kernel": None}
    device = next((p.device for p in model.parameters()), torch.device("cpu"))
    size = _probe_size(model)
    pixels = size * size
    compositor = None
    if isinstance(model, Denoiser):
        # The batch must match the model's inputs, whatever the caller guessed.
        in_channels = model.in_channels or in_channels
        branches = model.branches or BRANCHES
        batch = random_batch(size, size, in_channels=in_channels, branches=branches, device=device)
        conv = 2 * _conv_macs(model, lambda: model(batch)) / pixels
        compositors = model.compositor_modules()
        if compositors is not None:
            compositor = 2 * _conv_macs(compositors, lambda: model(batch)) / pixels
        kernel = float(model.kernel_flops_per_pixel())
    else:
        x = torch.rand(1, in_channels, size, size, device=device)
        conv = 2 * _conv_macs(model, lambda: model(x)) / pixels
        kernel = 0.0
    flops = {"total": conv + kernel, "conv": conv, "kernel": kernel}
    return flops if compositor is None else flops | {"compositor": compositor}


def _fmt(x: float | None, digits: int = 0) -> str:
    return "n/a" if x is None else f"{x:,.{digits}f}"


def _parameter_lines(model: nn.Module) -> list[str]:
    total = count_parameters(model)
    if not isinstance(model, BranchDenoiser):
        return [f"parameters: {total:,}"]
    if model.shared:
        return [f"parameters: {total:,} (one network shared by the {' and '.join(model.branches)} branches)"]
    per = ", ".join(f"{b} {count_parameters(model.net(b)):,}" for b in model.branches)
    return [f"parameters: {total:,} ({per})"]


def model_summary(
    model: nn.Module, model_cfg: Mapping[str, Any], frame: tuple[int, int] = (1280, 720)
) -> str:
    """The text `python -m src.run stage=summary` prints: architecture, parameters, FLOPs per pixel and
    GFLOPs for one `frame` (width, height; default the KPCN set's 1280x720, Bako et al. 2017)."""
    flops = flops_per_pixel(model)
    width, height = frame
    frame_gflops = None if flops["total"] is None else flops["total"] * width * height / 1e9
    name, target = model_cfg.get("name", "?"), model_cfg.get("_target_", "?")
    lines = [f"model: {name} ({target}, learned {bool(model.learned)})", str(model)]
    lines += _parameter_lines(model)
    breakdown = ""
    if flops["conv"] is not None:
        compositor = flops.get("compositor")
        of_which = f" (of which scale compositors {_fmt(compositor)})" if compositor else ""
        what = "kernel application and composition" if compositor else "kernel application"
        breakdown = f" total = conv {_fmt(flops['conv'])}{of_which} + {what} {_fmt(flops['kernel'])}"
    if isinstance(model, Denoiser) and model.branches and tuple(model.branches) != BRANCHES:
        lines.append(f"inputs: the {', '.join(model.branches)} branch, in_channels {model.in_channels}")
    lines.append(f"FLOPs per pixel: {_fmt(flops['total'])}{breakdown}")
    lines.append(f"GFLOPs per {width}x{height} frame: {_fmt(frame_gflops, 1)}")
    return "\n".join(lines)
