"""The fitness of the genetic-programming filter search (Davletaliyev 2016, Sec. 3.2.3): the mean over the
training images of relMSE(filtered) / relMSE(noisy), relMSE of Eq. 3.5 (its m/2 factor cancels in the
ratio); an undefined expression (NaN/Inf weights or a zero weight sum on any image) gets the worst
fitness, `WORST` = the largest float. Expressions are filtered in batches by `src.gp.evaluate`.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Mapping, Sequence

import torch
from deap import gp

from src.errors import DataError
from src.gp.evaluate import filter_images

WORST = sys.float_info.max
"""Fitness of an undefined expression (Davletaliyev 2016, Sec. 3.2.3: "maximum float")."""


def relative_error(x: torch.Tensor, y: torch.Tensor, eps: float) -> torch.Tensor:
    """Per image (N,): mean over pixels of sum over channels of (x - y)^2 / (y^2 + eps), i.e. Eq. 3.5
    (`src.metrics.image.relmse_spp`) without its m/2 factor, which cancels in the fitness ratio."""
    return ((x - y).square() / (y.square() + eps)).sum(1).flatten(1).mean(1)


class Fitness:
    """The thesis's fitness (Sec. 3.2.3) of many trees on fixed training images, `tree_batch` trees per
    `filter_images` call (they share features and common sub-expressions).

    `features`: terminal -> (N, C, H, W) as `src.gp.evaluate.filter_images` takes them; `color`,
    `reference`: (N, 3, H, W) linear HDR."""

    def __init__(
        self,
        features: Mapping[str, torch.Tensor],
        color: torch.Tensor,
        reference: torch.Tensor,
        radius: int,
        eps: float = 0.01,
        tree_batch: int = 16,
    ) -> None:
        self.features, self.color, self.reference = dict(features), color, reference
        self.radius, self.eps, self.tree_batch = int(radius), float(eps), int(tree_batch)
        self.noisy = relative_error(color, reference, self.eps)
        if not bool((self.noisy > 0).all()):
            raise DataError("search: a training image's noisy colour equals its reference (relMSE 0)")
        self.evaluations = 0

    def __call__(self, trees: Sequence[gp.PrimitiveTree]) -> list[float]:
        out: list[float] = []
        for start in range(0, len(trees), self.tree_batch):
            chunk = trees[start : start + self.tree_batch]
            result = filter_images(chunk, self.features, self.color, self.radius)
            for filtered, valid in zip(result.color, result.valid, strict=True):
                value = float((relative_error(filtered, self.reference, self.eps) / self.noisy).mean())
                out.append(value if bool(valid.all()) and math.isfinite(value) else WORST)
        self.evaluations += len(trees)
        return out
