"""How a kind of data splits the colour into the branches a denoiser filters, and how a model's branch
outputs become linear colour again: the part of the batch contract (`src.models.denoise.base`) that
differs between the denoising kinds.

- `KpcnSplit` (still images): Bako et al. 2017 Sec. 4.1 / the Zagreb thesis (Bunjevac 2019) Sec. 4.3: a
  diffuse branch divided by the albedo and a specular branch under log(1 + s); linear colour is
  c = (albedo + eps) * d' + exp(s') - 1 (`rebuild_color`).
- `RadianceTransform` (sequences): one `radiance` branch under the sequences' radiance transform
  (log-modulus sign(x) log(1 + |x|) by default, Zhu et al. 2023), inverted (`inverse_volume_transform`).

A model that returns {"color": ...} returns linear colour already (filters, the U-Net KPCN).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch

from src.data.transforms import inverse_volume_transform, rebuild_color

Tensors = Mapping[str, torch.Tensor]


class KpcnSplit:
    """Diffuse (over albedo + eps) and specular (log1p) branches of the still images."""

    branches = ("diffuse", "specular")

    def __init__(self, eps: float) -> None:
        self.eps = float(eps)

    def to_linear(self, outputs: Tensors, batch: Tensors) -> torch.Tensor:
        return rebuild_color(outputs["diffuse"], outputs["specular"], batch["albedo"], self.eps)


class RadianceTransform:
    """The one `radiance` branch of the sequences under `transform`
    (`dataset.preprocess.volume_transform`)."""

    branches = ("radiance",)

    def __init__(self, transform: str) -> None:
        self.transform = str(transform)

    def to_linear(self, outputs: Tensors, batch: Tensors) -> torch.Tensor:
        return inverse_volume_transform(outputs["radiance"], self.transform)
