"""The fitness of the genetic-programming filter search (Davletaliyev 2016, Sec. 3.2.3): the mean over the
training images of relMSE(filtered) / relMSE(noisy), relMSE of Eq. 3.5 (its m/2 factor cancels in the
ratio); an undefined expression (NaN/Inf weights or a zero weight sum on any image) gets the worst
fitness, `WORST` = the largest float. Expressions are filtered in batches by `src.gp.evaluate`.

An optional bias guard (`bias_guard`, weight w >= 0; 0, the default, is off, as in the thesis, which has
no such term) adds w * |mean(filtered) / mean(noisy) - 1| to each image's term before the mean over the
images, means over pixels and channels. relMSE weighs an error by 1 / (reference^2 + eps), so a filter
that darkens bright pixels towards their dark neighbours can lower it while losing energy (issue 32: the
cpu search's best kept 0.895 / 0.923 of the reference's mean). The guard compares with the noisy input,
an unbiased estimate of the reference the search may read, not with the reference itself.
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
    `filter_images` call (they share features and common sub-expressions), plus the optional bias guard.

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
        bias_guard: float = 0.0,
    ) -> None:
        self.features, self.color, self.reference = dict(features), color, reference
        self.radius, self.eps, self.tree_batch = int(radius), float(eps), int(tree_batch)
        self.bias_guard = float(bias_guard)
        if not self.bias_guard >= 0.0:
            raise ValueError(f"Fitness: bias_guard={bias_guard}; expected a weight >= 0")
        self.noisy = relative_error(color, reference, self.eps)
        if not bool((self.noisy > 0).all()):
            raise DataError("search: a training image's noisy colour equals its reference (relMSE 0)")
        self.noisy_mean = color.flatten(1).mean(1)  # (N,): mean over pixels and channels
        if self.bias_guard > 0 and not bool((self.noisy_mean > 0).all()):
            raise DataError(
                "search: task.search.bias_guard > 0 but a training image's noisy mean is not positive"
            )
        self.evaluations = 0

    def __call__(self, trees: Sequence[gp.PrimitiveTree]) -> list[float]:
        out: list[float] = []
        for start in range(0, len(trees), self.tree_batch):
            chunk = trees[start : start + self.tree_batch]
            result = filter_images(chunk, self.features, self.color, self.radius)
            for filtered, valid in zip(result.color, result.valid, strict=True):
                terms = relative_error(filtered, self.reference, self.eps) / self.noisy
                if self.bias_guard > 0:
                    terms = (
                        terms + self.bias_guard * (filtered.flatten(1).mean(1) / self.noisy_mean - 1).abs()
                    )
                value = float(terms.mean())
                out.append(value if bool(valid.all()) and math.isfinite(value) else WORST)
        self.evaluations += len(trees)
        return out
