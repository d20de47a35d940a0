"""Per-pixel sample statistics from the film's running means.

With a box reconstruction filter each sample lands in exactly one pixel with weight 1, so the film
holds the sample mean m = (1/n) sum x_i and, for the squared AOVs, the raw second moment
s = (1/n) sum x_i^2. Passes of different sizes are merged in float64 to limit cancellation.
"""

from __future__ import annotations

import numpy as np


def variance_of_mean(mean: np.ndarray, second_moment: np.ndarray, n: int) -> np.ndarray:
    """Unbiased estimate of Var[pixel mean] from n samples: (s - m^2) / (n - 1).

    The unbiased sample variance is n / (n - 1) * (s - m^2); dividing by n gives the variance of
    the mean. Negative values from floating-point cancellation are clamped to 0. Multi-channel
    buffers (last axis) are averaged over channels, as in the KPCN data (one variance per buffer).
    """
    if n < 2:
        raise ValueError(f"the variance of the mean needs at least 2 samples per pixel, got {n}")
    var = np.maximum(second_moment - np.square(mean), 0.0) / (n - 1)
    return var.mean(axis=-1, keepdims=True)


class MomentAccumulator:
    """Merges per-pass (mean, second moment) images weighted by their sample counts, in float64."""

    def __init__(self) -> None:
        self.n = 0
        self.sum: np.ndarray | None = None

    def add(self, pass_means: np.ndarray, spp: int) -> None:
        """Add one pass: ``pass_means`` (H, W, C) are per-pixel sample means over ``spp`` samples."""
        weighted = pass_means.astype(np.float64) * spp
        self.sum = weighted if self.sum is None else self.sum + weighted
        self.n += spp

    def mean(self) -> np.ndarray:
        if self.sum is None:
            raise ValueError("no pass added")
        return self.sum / self.n
