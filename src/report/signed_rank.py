"""One estimator for a paired comparison: the Hodges-Lehmann shift, the exact Wilcoxon signed-rank test
and the confidence interval that inverts it (Hollander, Wolfe & Chicken, Nonparametric Statistical
Methods, 3rd ed., Sec. 3.1-3.2). Direction, size and significance come from the same ranks, so a mean
dragged by one heavy-tailed outlier (relMSE) cannot point one way while the test points the other.

For paired differences d_1..d_n:
- the Walsh averages (d_i + d_j) / 2, i <= j, number N = n (n + 1) / 2;
- the estimate is their median (Hodges-Lehmann, HWC Eq. 3.15);
- under H0 (symmetry about 0) the count of positive Walsh averages is Wilcoxon's T+ (Tukey's identity,
  HWC Comment 3.17), whose null law is that of the sum of a random subset of {1..n} (HWC Sec. 3.1);
- the (1 - alpha) interval is [W_(k), W_(N+1-k)], k the largest integer with P(T+ <= k - 1) <= alpha / 2
  (HWC Eq. 3.21);
- the two-sided p is 2 min(P(T+ <= t_-), P(T+ <= t_+)), t_- the Walsh averages <= 0 and t_+ those >= 0.
  A zero Walsh average counts against both sides, so that p <= alpha exactly when the interval excludes
  0: the test and the interval can never disagree, ties included.

The null law is exact (a convolution over the ranks) up to `EXACT_MAX` items and the normal
approximation with continuity correction beyond. A failed output is an infinite difference: it is the
worst rank on its item and moves the estimate the way a rank statistic should, by one rank.
scipy.stats.wilcoxon gives the p-value but neither the estimate nor the interval, and its tie handling
would not match the interval's; statsmodels is not a dependency. Hence this module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cache

import numpy as np

#: Up to this many items the null law of T+ is computed exactly (vectors of n (n + 1) / 2 + 1 numbers).
EXACT_MAX = 400


@cache
def signed_rank_cdf(n: int) -> np.ndarray:
    """P(T+ <= t) for t = 0..n(n+1)/2 under H0: T+ is the sum of each rank 1..n kept with probability
    1/2 independently (HWC Sec. 3.1), so its law is the convolution of n two-point laws. Exact for
    n <= EXACT_MAX, else the normal approximation (mean n(n+1)/4, variance n(n+1)(2n+1)/24)."""
    if n < 0:
        raise ValueError(f"signed_rank_cdf: n = {n}; expected n >= 0")
    total = n * (n + 1) // 2
    if n > EXACT_MAX:
        from scipy.stats import norm

        mean, sd = total / 2, math.sqrt(n * (n + 1) * (2 * n + 1) / 24)
        return norm.cdf((np.arange(total + 1) + 0.5 - mean) / sd)
    law = np.zeros(total + 1)
    law[0] = 1.0
    for rank in range(1, n + 1):
        law[rank:] = 0.5 * law[rank:] + 0.5 * law[:-rank].copy()
        law[:rank] *= 0.5
    return np.minimum(np.cumsum(law), 1.0)


def walsh_averages(d: np.ndarray) -> np.ndarray:
    """(d_i + d_j) / 2 for i <= j, sorted. An infinite difference (a failed output) stays infinite; a
    failure of each arm on two items averages to 0 (neither arm better)."""
    i, j = np.triu_indices(len(d))
    with np.errstate(invalid="ignore"):
        averages = (d[i] + d[j]) / 2.0
    return np.sort(np.nan_to_num(averages, nan=0.0, posinf=np.inf, neginf=-np.inf))


def smallest_p(n: int) -> float:
    """The smallest two-sided p a signed-rank test over n items can give: 2 / 2^n (all of one sign)."""
    return min(1.0, 2.0 / 2.0**n)


def min_items(alpha: float) -> int:
    """The fewest items with which a two-sided signed-rank test can reach p <= alpha."""
    n = 1
    while smallest_p(n) > alpha:
        n += 1
    return n


@dataclass(frozen=True)
class SignedRank:
    """The paired comparison of n differences (a - b, or log a - log b): `estimate` (Hodges-Lehmann),
    the `level` interval [`low`, `high`] (infinite when n is too small for that level), the two-sided
    `p_value`, and how many differences favour each side (`positive`, `negative`)."""

    n: int
    estimate: float
    low: float
    high: float
    p_value: float
    level: float
    positive: int
    negative: int

    def significant(self, alpha: float) -> bool:
        """p <= alpha; the same as the (1 - alpha) interval excluding 0."""
        return self.p_value <= alpha


def signed_rank(d, alpha: float = 0.05) -> SignedRank:
    """The signed-rank comparison of the differences `d` at level 1 - `alpha` (module docstring). NaN
    differences are not allowed (a failure is +-inf, a missing pair is left out before)."""
    d = np.asarray(d, dtype=float)
    if d.ndim != 1 or len(d) < 1 or np.isnan(d).any():
        raise ValueError(f"signed_rank: {d!r}; expected a non-empty vector of differences without NaN")
    n = len(d)
    cdf = signed_rank_cdf(n)
    walsh = walsh_averages(d)
    t_neg, t_pos = int((walsh <= 0).sum()), int((walsh >= 0).sum())
    p = min(1.0, 2.0 * float(min(cdf[t_neg], cdf[t_pos])))
    k = int(np.searchsorted(cdf, alpha / 2.0, side="right"))  # cdf[k - 1] <= alpha / 2 < cdf[k]
    low, high = (float(walsh[k - 1]), float(walsh[len(walsh) - k])) if k >= 1 else (-math.inf, math.inf)
    return SignedRank(
        n=n,
        estimate=float(np.median(walsh)),
        low=low,
        high=high,
        p_value=p,
        level=1.0 - alpha,
        positive=int((d > 0).sum()),
        negative=int((d < 0).sum()),
    )


def benjamini_hochberg(p_values) -> np.ndarray:
    """Benjamini-Hochberg adjusted p-values (scipy's `false_discovery_control`), NaN kept as NaN."""
    from scipy.stats import false_discovery_control

    p = np.asarray(p_values, dtype=float)
    adjusted = np.full(p.shape, np.nan)
    finite = ~np.isnan(p)
    if finite.any():
        adjusted[finite] = false_discovery_control(p[finite], method="bh")
    return adjusted


def replicates_for_power(sd: float, effect: float, alpha: float, power: float = 0.8) -> int | None:
    """About how many replicates a signed-rank test needs to detect a shift `effect` with `power`, when
    the replicate differences spread with standard deviation `sd`: the paired t-test's normal-theory
    count divided by the signed-rank test's asymptotic relative efficiency 3/pi (HWC Sec. 3.11), and
    never below `min_items(alpha)`. None when it cannot be said (no spread measured, no effect)."""
    from scipy.stats import norm

    if not (math.isfinite(sd) and math.isfinite(effect)) or sd <= 0 or effect == 0:
        return None
    z = norm.ppf(1 - alpha / 2) + norm.ppf(power)
    return max(min_items(alpha), math.ceil((z * sd / abs(effect)) ** 2 / (3 / math.pi)))
