"""Timing one denoiser on a frame: a learned model (and a kernel model's networks alone), or OIDN."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from src.bench.model_configs import load_model_config
from src.errors import one_line
from src.models.denoise.base import Denoiser
from src.models.denoise.models import BRANCHES, BranchDenoiser, infer_tiled
from src.models.denoise.summary import flops_per_pixel, random_batch
from src.models.instantiate import build_method
from src.models.parameters import count_parameters


@dataclass
class Row:
    """One line of the result table."""

    name: str
    seconds: float | None  # median seconds per frame
    flops_per_pixel: float | None = None
    params: int | None = None
    note: str = ""


class NetworkOnly(nn.Module):
    """A kernel model's networks without `apply_kernel` (same tiles, same halo): the "conv stack alone"
    that the kernel-application overhead is measured against."""

    learned = True

    def __init__(self, model: BranchDenoiser) -> None:
        super().__init__()
        self.model = model

    @property
    def halo(self) -> int:
        return self.model.halo

    def forward(self, batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return self.model.network_outputs(batch)


def frame_tiles(size: int, tile: int) -> list[slice]:
    step = size if tile <= 0 else tile
    return [slice(start, min(start + step, size)) for start in range(0, size, step)]


def bench_model(name: str, cfg: Mapping[str, Any], batch, tile: int, device: torch.device, timer, seed: int):
    """Rows for one model: itself, and for kernel models its networks alone (timed interleaved). A model of
    other branches than the still images' (the U-Net KPCN: the sequences' radiance) gets a random batch of
    its branches of the same size, with its own `in_channels` (`task.volume_features` of the profile)."""
    torch.manual_seed(seed)
    model: Denoiser = build_method(cfg).to(device).eval()
    if model.branches and tuple(model.branches) != BRANCHES:
        height, width = next(iter(batch.values())).shape[-2:]
        generator = torch.Generator().manual_seed(seed)
        batch = random_batch(
            height,
            width,
            in_channels=model.in_channels,
            branches=model.branches,
            generator=generator,
            device=device,
        )
    flops = flops_per_pixel(model)
    params = count_parameters(model)
    runs = [lambda: infer_tiled(model, batch, tile)]
    if isinstance(model, BranchDenoiser) and model.output == "kernel":
        net = NetworkOnly(model)
        runs.append(lambda: infer_tiled(net, batch, tile))
    seconds = timer(runs)
    note = cfg["_target_"].rsplit(".", 1)[-1] + (f", output {cfg['output']}" if "output" in cfg else "")
    rows = [Row(name, seconds[0], flops["total"], params, note)]
    if len(seconds) > 1:
        rows.append(Row(f"{name} (net only)", seconds[1], flops["conv"], params, "no apply_kernel"))
    return rows


def bench_oidn(profile: str, batch, timer) -> Row:
    """OIDN on the full frame (it is never tiled), or a row saying why it cannot run here."""
    try:
        model = build_method(load_model_config("oidn", profile))
        seconds = timer([lambda: infer_tiled(model, batch, 0)])[0]
        return Row("oidn", seconds, note="pyoidn, full frame")
    except Exception as err:  # import failure, missing native library, unsupported device...
        reason = one_line(err)
        return Row("oidn", None, note=f"unavailable ({reason})")
