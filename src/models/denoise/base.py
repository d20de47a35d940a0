"""The one interface every denoiser (learned or not) implements, so they share training, evaluation,
benchmarks and report tables.

A batch is a dict of float32 (N, C, H, W) tensors, as `src.data.denoise_dataset` yields them:

    diffuse_in, specular_in   the `task.features` channels (`src.data.features`; the paper's 28 by
                              default), in the order configured, NOT whitened: a model
                              that whitens holds the statistics as buffers and applies them itself, so a
                              checkpoint is self-contained
    diffuse_t, specular_t     transformed noisy colours (d / (albedo + eps), log(1 + s)): what kernels filter
    albedo, normal            noisy albedo (3), world-space shading normal in [-1, 1] (3)
    depth                     depth normalised to [0, 1] by the image maximum (1)
    color, reference          noisy and reference colour, linear HDR (3)
    diffuse_target, specular_target   transformed reference (training targets)

`Denoiser.forward(batch)` returns a dict:
    learned models: {"diffuse": ..., "specular": ...} in the transformed space (then `final_color`
                    rebuilds linear colour with the inverse transform);
    filters:        {"color": ...} linear HDR colour.
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from src.data.kpcn_preprocess import rebuild_color

Batch = Mapping[str, torch.Tensor]


class Denoiser(nn.Module):
    """Base class. `learned` says whether the train stage fits it; `halo` is the number of pixels of
    context one output pixel depends on (receptive-field radius), which tiled inference pads tiles by."""

    learned: bool = True

    @property
    def halo(self) -> int:
        raise NotImplementedError

    def forward(self, batch: Batch) -> dict[str, torch.Tensor]:
        raise NotImplementedError


def final_color(outputs: Mapping[str, torch.Tensor], batch: Batch, eps: float) -> torch.Tensor:
    """Linear HDR colour from a denoiser's outputs: its "color", or the inverse transform of its
    diffuse/specular (c = (albedo + eps) * d' + exp(s') - 1)."""
    if "color" in outputs:
        return outputs["color"]
    return rebuild_color(outputs["diffuse"], outputs["specular"], batch["albedo"], eps)
