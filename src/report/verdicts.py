"""A claim's status from its numbers: pure functions of the per-item scores of the compared arms, so the
ledger (`src.report.ledger`) never types a status by hand and every rule is tested on its own.

- `better_verdict`: arm a beats arm b. Paired over the items both were scored on (the same seed and
  held-out image, or the same benchmark round), two-sided Wilcoxon signed-rank (`src.report.paired`):
  **reproduced** when the difference is significant in the claimed direction and at least the published
  `size`; **direction only** when significant in that direction but smaller; **not reproduced** when
  significant the other way; **not distinguishable** when p >= alpha (a signed-rank test over n items
  cannot give p below 2 / 2^n, so fewer than `min_items(alpha)` items can never show a difference: the
  verdict says so).
- `comparable_verdict` ("comparable quality"): an equivalence check. **Reproduced** when the 95 %
  t-interval of the mean paired difference lies inside +-tolerance, **not reproduced** when it lies
  wholly outside, else **not distinguishable**.
- `agreement_verdict`: published numbers, as NerfBaselines checks reproductions (PSNR within 0.2 dB,
  SSIM within 0.05): each case's mean against its published value. **Reproduced** when every case that
  ran is within the tolerance, **not reproduced** when one is not.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from src.report.paired import paired_difference

REPRODUCED = "reproduced"
DIRECTION_ONLY = "direction only"
NOT_REPRODUCED = "not reproduced"
NOT_DISTINGUISHABLE = "not distinguishable"
NOT_RUN = "not run"
STATUSES = (REPRODUCED, DIRECTION_ONLY, NOT_REPRODUCED, NOT_DISTINGUISHABLE, NOT_RUN)


@dataclass(frozen=True)
class Verdict:
    """A claim's status, the one-line account of the numbers behind it, and the items it rests on."""

    status: str
    numbers: str
    items: int = 0


def min_items(alpha: float) -> int:
    """The fewest items with which a two-sided signed-rank test can reach p < alpha: its smallest p over
    n items is 2 / 2^n (every difference of one sign)."""
    return math.floor(math.log2(2 / alpha)) + 1


def _spread(values: pd.Series) -> str:
    sd = float(values.std(ddof=1)) if len(values) > 1 else 0.0
    return f"{float(values.mean()):.4g} ± {sd:.2g}"


def better_verdict(
    a: pd.Series, b: pd.Series, names: tuple[str, str], higher: bool, log: bool, size: float, alpha: float
) -> Verdict:
    """Whether arm a (scores `a`, one per item, indexed by item) beats arm b (module docstring). `size`:
    the published effect, in the metric's units, or as a factor (>= 1) when `log`; 0: any."""
    common = a.index.intersection(b.index)
    if len(common) < 2:
        return Verdict(NOT_RUN, f"{len(common)} item(s) scored in both arms; a paired test needs 2 or more")
    result = paired_difference(a[common], b[common], log=log)
    effect = result.mean_difference if higher else -result.mean_difference
    wins, losses = (result.a_higher, result.b_higher) if higher else (result.b_higher, result.a_higher)
    if log:
        shown_size = f"{names[0]} better by a factor {math.exp(effect):.4g} (geometric mean)"
        big_enough = math.exp(effect) >= max(size, 1.0)
    else:
        shown_size = f"{names[0]} - {names[1]} = {result.mean_difference:+.4g}"
        big_enough = effect >= size
    numbers = (
        f"{shown_size} over {result.n} paired items ({wins} favour {names[0]}, {losses} {names[1]}; "
        f"Wilcoxon p = {result.p_value:.2g}); "
        f"{names[0]} {_spread(a[common])}, {names[1]} {_spread(b[common])}"
    )
    if size:
        numbers += f"; published size {size:g}" + ("x" if log else "")
    if not result.shown(alpha):
        floor = min_items(alpha)
        if result.n < floor:
            numbers += f"; {result.n} items cannot reach p < {alpha:g} (needs {floor} or more)"
        return Verdict(NOT_DISTINGUISHABLE, numbers, result.n)
    if effect < 0:
        return Verdict(NOT_REPRODUCED, numbers, result.n)
    return Verdict(REPRODUCED if big_enough else DIRECTION_ONLY, numbers, result.n)


def comparable_verdict(
    a: pd.Series, b: pd.Series, names: tuple[str, str], log: bool, tolerance: float, level: float = 0.95
) -> Verdict:
    """Whether arms a and b are equivalent within `tolerance` (metric units; a log ratio when `log`): the
    `level` t-interval of the mean paired difference against +-tolerance (module docstring)."""
    from scipy import stats  # lazy: only the ledger needs it

    common = a.index.intersection(b.index)
    if len(common) < 2:
        return Verdict(NOT_RUN, f"{len(common)} item(s) scored in both arms; an interval needs 2 or more")
    x, y = a[common].to_numpy(float), b[common].to_numpy(float)
    d = np.log(x) - np.log(y) if log else x - y
    mean, sem = float(d.mean()), float(d.std(ddof=1) / math.sqrt(len(d)))
    half = float(stats.t.ppf(0.5 + level / 2, len(d) - 1)) * sem
    lo, hi = mean - half, mean + half
    what = f"log({names[0]} / {names[1]})" if log else f"{names[0]} - {names[1]}"
    numbers = (
        f"{what} = {mean:+.4g}, {level:.0%} interval [{lo:+.4g}, {hi:+.4g}] over {len(d)} paired items, "
        f"tolerance ±{tolerance:g}; {names[0]} {_spread(a[common])}, {names[1]} {_spread(b[common])}"
    )
    if -tolerance <= lo and hi <= tolerance:
        return Verdict(REPRODUCED, numbers, len(d))
    if lo > tolerance or hi < -tolerance:
        return Verdict(NOT_REPRODUCED, numbers, len(d))
    return Verdict(NOT_DISTINGUISHABLE, numbers, len(d))


def agreement_verdict(cases: Sequence[tuple[str, pd.Series | None, float]], tolerance: float) -> Verdict:
    """Whether each case's measured mean is within `tolerance` of its published value. `cases`: (label,
    the case's values over seeds/items or None when it did not run, published value)."""
    ran = [(label, values, value) for label, values, value in cases if values is not None and len(values)]
    if not ran:
        return Verdict(NOT_RUN, f"none of the {len(cases)} published case(s) has runs")
    parts, within = [], 0
    for label, values, published in ran:
        mean = float(values.mean())
        ok = abs(mean - published) <= tolerance
        within += ok
        parts.append(f"{label} {mean:.4g} vs {published:g}" + ("" if ok else " (outside)"))
    numbers = f"{within} of {len(ran)} case(s) within ±{tolerance:g}"
    if len(ran) < len(cases):
        numbers += f" ({len(cases) - len(ran)} of {len(cases)} not run)"
    numbers += ": " + "; ".join(parts)
    return Verdict(REPRODUCED if within == len(ran) else NOT_REPRODUCED, numbers, len(ran))
