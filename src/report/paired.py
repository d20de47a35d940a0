"""Paired comparison of two arms of a study on the same items (the same seed and held-out image in both
arms): a difference between methods is only a finding when it stands out of the differences between
seeds and images, which a paired test measures and a table of means does not.

`paired_difference(a, b)`: the per-item differences d = a - b (or log a - log b for a ratio metric such as
relMSE, so that "B is 20 % lower" weighs the same on an easy and a hard image), their mean, how many items
favour each arm, and the two-sided Wilcoxon signed-rank p-value of the differences (scipy: exact for
fewer than 50 items without ties, the normal approximation beyond). With a handful of items the smallest
p a signed-rank test can give is 2 / 2^n (n = 6: 0.031), so "not shown" at a small budget is what the
test must say when it cannot separate the arms.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from src.errors import DataError


@dataclass(frozen=True)
class Paired:
    """`n` items; `mean_difference` the mean of d (log units with `log`: exp of it is the geometric-mean
    ratio a / b); `a_higher` / `b_higher` the items where d > 0 / d < 0; `p_value` two-sided Wilcoxon
    signed-rank (NaN when every d is 0 or n < 2)."""

    n: int
    mean_difference: float
    a_higher: int
    b_higher: int
    p_value: float
    log: bool

    @property
    def ratio(self) -> float:
        """The geometric-mean ratio a / b (`log` only)."""
        if not self.log:
            raise ValueError("ratio: a paired difference of logs only")
        return math.exp(self.mean_difference)

    def shown(self, alpha: float = 0.05) -> bool:
        """Whether the difference is significant at `alpha` (two-sided)."""
        return bool(self.p_value < alpha)


def paired_difference(a: Sequence[float], b: Sequence[float], log: bool = False) -> Paired:
    """The paired comparison of `a` and `b`, one value per item in the same order (module docstring).
    A length mismatch, a non-finite value, or (with `log`) a value <= 0 is a one-line DataError."""
    from scipy import stats  # lazy: only the studies that compare arms need it

    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    if x.shape != y.shape or x.ndim != 1:
        raise DataError(f"paired comparison: {x.shape} against {y.shape} values; expected one per item")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise DataError("paired comparison: a value is NaN or infinite; expected finite values")
    if log and not ((x > 0).all() and (y > 0).all()):
        raise DataError("paired comparison of logs: a value is <= 0; expected positive values")
    d = np.log(x) - np.log(y) if log else x - y
    p = float("nan")
    if len(d) >= 2 and np.any(d != 0):
        p = float(stats.wilcoxon(d).pvalue)
    return Paired(len(d), float(d.mean()), int((d > 0).sum()), int((d < 0).sum()), p, log)
