"""A claim's status from its numbers: pure functions of the compared arms' per-replicate differences, so
the ledger (`src.report.ledger`) never types a status by hand and every rule is tested on its own.

A replicate is what varies independently (the ledger decides it: a training seed for learned arms, with
the held-out images nested in it; an image for deterministic arms). Direction, size and test come from
one estimator, the Hodges-Lehmann shift with the signed-rank test and the interval that inverts it
(`src.report.signed_rank`), at level 1 - alpha.

- `better_verdict` (arm a beats arm b, optionally by a published `size`): **reproduced** when the interval
  lies on the claimed side of 0 and does not lie wholly below the published size; **direction only** when
  it lies on the claimed side but wholly below the size (the data exclude the published effect); **not
  reproduced** when it lies on the other side; **not distinguishable** when it contains 0.
- `comparable_verdict` (an equivalence): **reproduced** when the interval lies inside +-tolerance, **not
  reproduced** when wholly outside, else **not distinguishable**.
- `not_worse_verdict` (a non-inferiority: arm a at worst on par with arm b): **reproduced** when the
  interval's lower end lies above -tolerance (a is not worse by more than the margin), **not reproduced**
  when its upper end lies below -tolerance (a is worse by more), else **not distinguishable**.
- `agreement_verdict` (published numbers): **reproduced** when every published case ran and each case's
  mean is within the tolerance of its value, **not reproduced** when one is not.
- Below a rule's minimum replication the status is **underpowered**, never a verdict: fewer replicates
  than a two-sided signed-rank test needs to reach p <= alpha at all (6 at 0.05), or, for agreement, a
  published case without runs. The row says what the design would need.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import pandas as pd

from src.report.signed_rank import min_items, replicates_for_power, signed_rank, smallest_p

REPRODUCED = "reproduced"
DIRECTION_ONLY = "direction only"
NOT_REPRODUCED = "not reproduced"
NOT_DISTINGUISHABLE = "not distinguishable"
UNDERPOWERED = "underpowered"
CONFOUNDED = "confounded"
NOT_RUN = "not run"
STATUSES = (
    REPRODUCED,
    DIRECTION_ONLY,
    NOT_REPRODUCED,
    NOT_DISTINGUISHABLE,
    UNDERPOWERED,
    CONFOUNDED,
    NOT_RUN,
)


@dataclass(frozen=True)
class Verdict:
    """A claim's status, the one-line account of the numbers behind it, the replicates it rests on, the
    test's raw p (NaN where the rule has none) and the estimate with its interval (the advantage of arm
    a: metric units, or a natural-log ratio for `log` claims)."""

    status: str
    numbers: str
    items: int = 0
    p_value: float = math.nan
    estimate: float = math.nan
    low: float = math.nan
    high: float = math.nan


def effect_text(value: float, log: bool, digits: int = 4) -> str:
    """A difference as printed: a factor for log claims, a signed number otherwise (`digits` significant)."""
    if log:
        return f"{math.exp(value):.{digits}g}x" if math.isfinite(value) else ("inf" if value > 0 else "0x")
    return f"{value:+.{digits}g}"


def _interval(result, log: bool) -> str:
    if not math.isfinite(result.low) and not math.isfinite(result.high):
        return f"no {result.level:.0%} interval with {result.n}"
    return f"{result.level:.0%} interval [{effect_text(result.low, log)}, {effect_text(result.high, log)}]"


def published_shift(size: float, log: bool) -> float | None:
    """A claim's published size on the compared scale: a plain size as it is, a log claim's factor (> 1)
    as its natural log; None where there is none (0, or a factor of at most 1)."""
    if not size or (log and size <= 1):
        return None
    return math.log(size) if log else size


def _needs(
    advantage: pd.Series, alpha: float, unit: str, size: float, log: bool
) -> str:  # what an underpowered design would need
    n, floor = len(advantage), min_items(alpha)
    text = (
        f"{n} {unit}: the smallest two-sided p with {n} is {smallest_p(n):.2g} > alpha {alpha:g}, so no "
        f"effect of any size can be shown; needs {floor} or more {unit}"
    )
    finite = advantage[np.isfinite(advantage)]
    target = published_shift(size, log)
    effect = target if target else (float(finite.median()) if len(finite) else math.nan)
    sd = float(finite.std(ddof=1)) if len(finite) > 1 else math.nan
    needed = replicates_for_power(sd, effect, alpha)
    if needed is not None:
        what = "the published size" if target else "the effect seen"
        text += f" (about {needed} to detect {what} with 80 % power at the spread seen, sd {sd:.2g})"
    return text


#: The verdict of a comparison no replicate was scored in by both arms.
NO_REPLICATE = Verdict(NOT_RUN, "no replicate scored in both arms")


def _tested(values: pd.Series, alpha: float) -> tuple[int, Any, dict[str, float]]:
    """(n, the signed-rank result, the Verdict fields it fills) of one value per replicate."""
    result = signed_rank(values.to_numpy(float), alpha)
    fields = dict(p_value=result.p_value, estimate=result.estimate, low=result.low, high=result.high)
    return len(values), result, {"items": len(values), **fields}


def better_verdict(
    advantage: pd.Series,
    names: tuple[str, str],
    log: bool,
    size: float,
    alpha: float,
    unit: str = "items",
    p_adjusted: float | None = None,
    nesting: str = "",
) -> Verdict:
    """Whether arm a beats arm b (module docstring). `advantage`: one value per replicate, positive where
    a is better (a - b when higher is better, b - a when lower; of logs when `log`), -inf where a's
    output failed and b's did not, +inf the other way. `size`: the published effect in metric units, or
    a factor (> 1) when `log`; 0: any. `p_adjusted`: the p after the family's correction, which decides
    significance when given (the interval stays the claim's own). `unit`: what a replicate is (seeds,
    images, rounds); `nesting`: what each holds, as printed after it."""
    if len(advantage) < 1:
        return NO_REPLICATE
    n, result, verdict = _tested(advantage, alpha)
    p = result.p_value if p_adjusted is None else p_adjusted
    threshold = published_shift(size, log)
    numbers = (
        f"{names[0]} better than {names[1]} by {effect_text(result.estimate, log)} (Hodges-Lehmann), "
        f"{_interval(result, log)} over {n} {unit}{nesting} ({result.positive} favour {names[0]}, "
        f"{result.negative} {names[1]}); signed-rank "
        f"p = {result.p_value:.2g}"
    )
    if p_adjusted is not None:
        numbers += f", adjusted p = {p_adjusted:.2g}"
    if threshold is not None:
        numbers += f"; published size {effect_text(threshold, log)}"
    if n < min_items(alpha):
        return Verdict(UNDERPOWERED, numbers + "; " + _needs(advantage, alpha, unit, size, log), **verdict)
    if p > alpha:
        return Verdict(NOT_DISTINGUISHABLE, numbers, **verdict)
    if result.high < 0:
        return Verdict(NOT_REPRODUCED, numbers, **verdict)
    if threshold is not None and result.high < threshold:
        return Verdict(DIRECTION_ONLY, numbers + " (the interval lies below it)", **verdict)
    return Verdict(REPRODUCED, numbers, **verdict)


def _cannot_bound(numbers: str, n: int, unit: str, level: float, alpha: float, verdict: dict) -> Verdict:
    """Underpowered: too few replicates for an interval that could lie inside a tolerance or margin."""
    return Verdict(
        UNDERPOWERED,
        f"{numbers}; {n} {unit} cannot bound the shift at {level:.0%}: needs {min_items(alpha)} or more",
        **verdict,
    )


def comparable_verdict(
    difference: pd.Series,
    names: tuple[str, str],
    log: bool,
    tolerance: float,
    alpha: float,
    unit: str = "items",
    nesting: str = "",
) -> Verdict:
    """Whether arms a and b are equivalent within `tolerance` (metric units; a natural-log ratio when
    `log`): the (1 - alpha) signed-rank interval of the shift a - b against +-tolerance. `difference`:
    a - b per replicate (+-inf where one arm failed)."""
    if len(difference) < 1:
        return NO_REPLICATE
    n, result, verdict = _tested(difference, alpha)
    verdict.pop("p_value")  # the test of a zero shift says nothing of equivalence
    what = f"log({names[0]} / {names[1]})" if log else f"{names[0]} - {names[1]}"
    numbers = (
        f"{what} = {result.estimate:+.4g} (Hodges-Lehmann), {_interval(result, False)} over {n} "
        f"{unit}{nesting}, tolerance ±{tolerance:g}"
    )
    if n < min_items(alpha):
        return _cannot_bound(numbers, n, unit, result.level, alpha, verdict)
    if -tolerance <= result.low and result.high <= tolerance:
        return Verdict(REPRODUCED, numbers, **verdict)
    if result.low > tolerance or result.high < -tolerance:
        return Verdict(NOT_REPRODUCED, numbers, **verdict)
    return Verdict(NOT_DISTINGUISHABLE, numbers, **verdict)


def not_worse_verdict(
    advantage: pd.Series,
    names: tuple[str, str],
    log: bool,
    tolerance: float,
    alpha: float,
    unit: str = "items",
    nesting: str = "",
) -> Verdict:
    """Whether arm a is at worst `tolerance` behind arm b (metric units; a natural-log ratio when `log`):
    the (1 - alpha) signed-rank interval of a's advantage against -tolerance (module docstring).
    `advantage`: per replicate, positive where a is better (+-inf where one arm failed)."""
    if len(advantage) < 1:
        return NO_REPLICATE
    n, result, verdict = _tested(advantage, alpha)
    numbers = (
        f"{names[0]} ahead of {names[1]} by {effect_text(result.estimate, log)} (Hodges-Lehmann), "
        f"{_interval(result, log)} over {n} {unit}{nesting}; margin: at most "
        f"{effect_text(tolerance, log).lstrip('+')} behind"
    )
    if n < min_items(alpha):
        return _cannot_bound(numbers, n, unit, result.level, alpha, verdict)
    if result.low >= -tolerance:
        return Verdict(REPRODUCED, numbers, **verdict)
    if result.high < -tolerance:
        return Verdict(NOT_REPRODUCED, numbers, **verdict)
    return Verdict(NOT_DISTINGUISHABLE, numbers, **verdict)


def agreement_verdict(cases: Sequence[tuple[str, pd.Series | None, float]], tolerance: float) -> Verdict:
    """Whether each published case's measured mean is within `tolerance` of its value. `cases`: (label,
    the case's values over seeds or None when it did not run, published value). Every case must run: a
    published table is reproduced as a whole, never from the cases that happened to run."""
    ran = [(label, values, value) for label, values, value in cases if values is not None and len(values)]
    if not ran:
        return Verdict(NOT_RUN, f"none of the {len(cases)} published case(s) has runs")
    parts, within = [], 0
    for label, values, published in ran:
        mean = float(values.mean())
        ok = abs(mean - published) <= tolerance
        within += ok
        parts.append(f"{label} {mean:.4g} vs {published:g} over {len(values)}" + ("" if ok else " (outside)"))
    numbers = f"{within} of {len(ran)} case(s) within ±{tolerance:g}: " + "; ".join(parts)
    if within < len(ran):
        return Verdict(NOT_REPRODUCED, numbers, len(ran))
    if len(ran) < len(cases):
        missing = [label for label, values, _ in cases if values is None or not len(values)]
        return Verdict(
            UNDERPOWERED, f"{numbers}; {len(missing)} of {len(cases)} not run: {', '.join(missing)}", len(ran)
        )
    return Verdict(REPRODUCED, numbers, len(ran))
