"""Paired comparison of two arms of a study on the same items (the same seed and held-out image in both
arms): a difference between methods is only a finding when it stands out of the differences between
seeds and images, which a paired test measures and a table of means does not.

`paired_difference(a, b)`: the per-item differences d = a - b (or log a - log b for a ratio metric such as
relMSE, so that "B is 20 % lower" weighs the same on an easy and a hard image), their mean, how many items
favour each arm, and the two-sided Wilcoxon signed-rank p-value of the differences (scipy: exact for
fewer than 50 items without ties, the normal approximation beyond). With a handful of items the smallest
p a signed-rank test can give is 2 / 2^n (n = 6: 0.031), so "not significant (n = 4)" at a small budget is
what the test must say when it cannot separate the arms.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from src.errors import DataError
from src.report.collect import DEFAULT_AXES, param_column
from src.report.tables import MISSING, RUNS_COLUMN, MetricSpec, axis_label


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

    def verdict(self, alpha: float = 0.05) -> str:
        """ "significant (n = 6)" or "not significant (n = 4)": the test's answer with the pairs it had (a
        reader sees at once when n was too small for any p below `alpha`)."""
        return f"{'significant' if self.shown(alpha) else 'not significant'} (n = {self.n})"


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


# ------------------------------------------------------------------ the paired table of a study

#: label -> (per-image score, compared as logs (a ratio metric), higher is better): the scores the paired
#: table compares each row with the best row on (`paired_table`).
PAIRED_METRICS: dict[str, tuple[str, bool, bool]] = {
    "relMSE / noisy": ("relmse_ratio", True, False),
    "PSNR": ("psnr", False, True),
    # sequences only (absent elsewhere): the flicker against the truth (data with a second reference) and
    # Noisebase's temporal PSNR
    "Flicker vs truth": ("flicker_unbiased", False, False),
    "tPSNR": ("tpsnr", False, True),
}


#: The significance level of the paired table's verdicts (two-sided).
PAIRED_ALPHA = 0.05


#: What identifies an item both rows were scored on: the seed and the held-out image.
PAIRED_ITEM = ("params.seed", "scene", "spp")


def item_means(part: pd.DataFrame, column: str, item: Sequence[str] = PAIRED_ITEM) -> pd.Series:
    """The scores in `column` of one compared row (or arm) `part`, one per item (the `item` columns, "-"
    for one `part` lacks); the mean where it has one item twice. Shared by the paired table and the
    ledger (src/report/ledger.py)."""
    index = [part[c].astype(str) if c in part else pd.Series("-", index=part.index) for c in item]
    scores = pd.to_numeric(part[column]).replace([np.inf, -np.inf], np.nan)
    return scores.groupby(index).mean().dropna()  # an infinite tPSNR (a copy of the reference) pairs nothing


def paired_table(
    images: pd.DataFrame, axes: Sequence[str] | None = None, alpha: float = PAIRED_ALPHA
) -> pd.DataFrame | None:
    """Each compared row against the best row, paired by seed and held-out image (`src.report.paired`):
    per metric of `PAIRED_METRICS` the row whose mean is best, then for every row the geometric-mean ratio
    (relMSE / noisy) or mean difference (PSNR, dB) against it over their common items, the two-sided
    Wilcoxon signed-rank p, and the verdict: `best`, `significant (n = ...)` (p < `alpha`) or `not
    significant (n = ...)` (the difference
    stays inside the spread of seeds and images); `pairs` is the item count of the first metric. A table
    of means cannot say whether a difference is a finding; this one can. None with fewer than two rows or
    no per-image scores."""
    if images.empty:
        return None
    labels = [axis_label(a) for a in (axes or DEFAULT_AXES)]
    columns = [param_column(a) for a in (axes or DEFAULT_AXES)]
    parts = [
        images[c].fillna(MISSING).astype(str) if c in images else pd.Series(MISSING, index=images.index)
        for c in columns
    ]
    keys = pd.Series(list(zip(*parts, strict=True)), index=images.index)  # one tuple per image row
    rows = list(dict.fromkeys(keys))
    if len(rows) < 2:
        return None
    row_images = {row: images[keys.map(lambda k, r=row: k == r)] for row in rows}
    table = pd.DataFrame(index=pd.MultiIndex.from_tuples(rows, names=labels))
    specs: dict[str, MetricSpec] = {}
    for label, (column, log_scale, higher) in PAIRED_METRICS.items():
        if f"metrics.{column}" not in images or images[f"metrics.{column}"].isna().all():
            continue
        scores = {row: item_means(row_images[row], f"metrics.{column}") for row in rows}
        log_scale = log_scale and all(bool((v > 0).all()) for v in scores.values())  # else differences
        scored = [row for row in rows if len(scores[row])]
        if not scored:
            continue
        means = {
            row: float(np.log(scores[row]).mean() if log_scale else scores[row].mean()) for row in scored
        }
        best = (max if higher else min)(scored, key=lambda r: means[r])
        against, p_values, verdicts, pairs = [], [], [], []
        for row in rows:
            common = scores[row].index.intersection(scores[best].index)
            if row == best or len(common) < 2:
                against.append(math.nan if row != best else (1.0 if log_scale else 0.0))
                p_values.append(math.nan)
                verdicts.append("best" if row == best else MISSING)
                pairs.append(len(common))
                continue
            result = paired_difference(scores[row][common], scores[best][common], log=log_scale)
            against.append(result.ratio if log_scale else result.mean_difference)
            p_values.append(result.p_value)
            verdicts.append(result.verdict(alpha))
            pairs.append(result.n)
        name = f"{label} vs best" + (" (ratio)" if log_scale else " (difference)")
        table[name], table[f"{label} p"], table[label] = against, p_values, verdicts
        # a ratio to 4 significant digits, a difference signed to 3: "-4.2e-05", never a "-0.000" that
        # hides the size behind a verdict
        number = "{:.4g}" if log_scale else "{:+.3g}"
        specs |= {name: ("", None, number), f"{label} p": ("", None, "{:.3g}"), label: ("", None, "{}")}
        if "pairs" not in table:
            table["pairs"] = pairs
            specs["pairs"] = ("", None, "{:,.0f}")
    if not specs:
        return None
    table[RUNS_COLUMN] = [
        int(row_images[row]["run_id"].nunique()) if "run_id" in images else len(row_images[row])
        for row in rows
    ]
    table.attrs["metrics"] = specs
    table.attrs["axes"] = labels
    return table
