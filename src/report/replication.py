"""The unit of replication of a comparison: what varies independently between two arms' scores.

A learned arm is replicated by its training: the (data seed, training seed) pair is the replicate, and
the held-out images scored under it are nested in it (the same network scores all of them). A
deterministic arm (a filter, OIDN, a fixed expression: `model.learned` false, or identical scores under
every seed) scores each image once, whatever the seed, so its replicate is the image. Pairing 3 seeds x
10 images as 30 items would count each image three times (pseudo-replication):

- both arms deterministic: one difference per held-out image;
- otherwise: one difference per replicate, the mean over the images both arms scored in it of the
  per-image differences (log ratios for `log` claims: the mean is then the log of the geometric-mean
  ratio); a deterministic arm's score of an image is paired with every replicate of the other arm;
- a benchmark's rounds are its replicates (the models are timed in alternating rounds).

A failed output (an undefined GP expression's NaN weights: the evaluation's `undefined` share > 0) is its
arm's worst outcome on that item, never dropped: the per-image difference is -inf against the arm that
failed (0 when both failed), and a replicate with such an image inherits it. A run that failed as a whole
(its training crashed or diverged: MLflow status FAILED, no finished rerun) is its arm's worst outcome on
that replicate: the replicate's difference is -inf against it (0 when both arms' runs failed). Where both
arms are deterministic (the images are the replicates) a failed run has no image to stand for, so it
counts only in the arm's undefined tally.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

#: What identifies a replicate of a learned arm: its data seed and training seed.
REPLICATE = ("params.data_seed", "params.seed")
#: The columns of an item nested in a replicate, per kind of score: a held-out image (a denoising
#: image is a scene at a sample count, a NeRF one a view of a scene); a run of one scene; a bench round.
NESTED = {
    "image": ("params.task.scene", "scene", "spp", "view"),
    "run": ("params.task.scene",),
    "round": (),
}
#: The column marking a score row that stands for a whole failed run (no item of it was scored), and the
#: item such a row is filed under.
RUN_FAILED_COLUMN = "run_failed"
RUN_FAILED = "(run failed)"
#: Scores equal to within this relative difference under every seed make an arm deterministic.
DETERMINISTIC_RTOL = 1e-9


@dataclass(frozen=True)
class Replicates:
    """One difference a - b per replicate (+-inf coded as above), what a replicate is (`unit`: seeds,
    images or rounds), how many seeds and images are behind it, and each arm's failed items."""

    difference: pd.Series
    unit: str
    seeds: int
    images: int
    undefined: tuple[int, int]
    deterministic: tuple[bool, bool]


def _key(frame: pd.DataFrame, columns: Sequence[str]) -> pd.Series:
    """One text key per row from `columns` ("-" for a column the frame lacks)."""
    parts = [frame[c].astype(str) if c in frame else pd.Series("-", index=frame.index) for c in columns]
    if not parts:
        return pd.Series("-", index=frame.index)
    key = parts[0]
    for part in parts[1:]:
        key = key + "|" + part
    return key


def arm_table(scores: pd.DataFrame, per: str) -> pd.DataFrame:
    """An arm's scores as (replicate, item) -> value, failed: the mean where an item was scored twice
    (a rerun folded in by the caller is not), failed when any copy failed. `scores` has `value` and,
    where the evaluation counts them, `failed`."""
    table = pd.DataFrame(
        {
            "replicate": _key(scores, ("round",) if per == "round" else REPLICATE),
            "item": _key(scores, NESTED[per]).where(~_run_failed(scores), RUN_FAILED),
            "value": pd.to_numeric(scores["value"], errors="coerce").astype(float),
            "failed": scores["failed"].astype(bool) if "failed" in scores else False,
        }
    )
    # An infinite score that is not a failure (tPSNR of an exact copy) pairs nothing, as in the reports.
    table.loc[~table["failed"] & ~np.isfinite(table["value"]), "value"] = np.nan
    table = table[table["failed"] | table["value"].notna()]
    return table.groupby(["replicate", "item"], sort=True).agg(
        value=("value", "mean"), failed=("failed", "any")
    )


def _run_failed(scores: pd.DataFrame) -> pd.Series:
    if RUN_FAILED_COLUMN not in scores:
        return pd.Series(False, index=scores.index)
    return scores[RUN_FAILED_COLUMN].fillna(False).astype(bool)


def is_deterministic(table: pd.DataFrame, learned: bool | None) -> bool:
    """Whether an arm scores each item the same under every replicate: said by its config (`learned`
    false: yes; true: no, its output depends on the seed even where a coarse score such as a count comes
    out equal under every seed) or, where the config does not say, seen (two or more replicates, every
    item's finite scores equal to `DETERMINISTIC_RTOL`)."""
    if learned is not None:
        return not learned
    if table.empty or table.index.get_level_values("replicate").nunique() < 2:
        return False
    values = table["value"].dropna()
    spread = values.groupby(level="item").agg(lambda v: float(v.max() - v.min()))
    scale = values.abs().groupby(level="item").max().clip(lower=1e-300)
    counts = values.groupby(level="item").size()
    return bool((counts >= 2).any() and (spread / scale <= DETERMINISTIC_RTOL).all())


def _item_differences(a: pd.DataFrame, b: pd.DataFrame, higher: bool, log: bool) -> pd.Series:
    """a - b per common index entry, with a failure the worst for its arm (module docstring)."""
    a, b = a.align(b, join="inner")
    with np.errstate(divide="ignore", invalid="ignore"):
        va, vb = (np.log(a["value"]), np.log(b["value"])) if log else (a["value"], b["value"])
        d = va - vb
    worst_for_a = -np.inf if higher else np.inf
    d = d.where(~a["failed"], worst_for_a).where(~b["failed"], -worst_for_a)
    return d.where(~(a["failed"] & b["failed"]), 0.0).dropna()


def _once_per_item(table: pd.DataFrame) -> pd.DataFrame:
    """A deterministic arm's scores, one per item (its replicates agree)."""
    return table.groupby(level="item").agg(value=("value", "first"), failed=("failed", "any"))


def replicate_differences(
    a_scores: pd.DataFrame,
    b_scores: pd.DataFrame,
    per: str,
    higher: bool,
    log: bool,
    learned: tuple[bool | None, bool | None] = (None, None),
) -> Replicates:
    """The per-replicate differences a - b of two arms' scores (module docstring). `learned`: each arm's
    `model.learned` where its runs log it."""
    a, b = arm_table(a_scores, per), arm_table(b_scores, per)
    undefined = (int(a["failed"].sum()), int(b["failed"].sum()))
    lost = (_lost_replicates(a), _lost_replicates(b))
    a, b = _scored_items(a), _scored_items(b)
    fixed = (is_deterministic(a, learned[0]), is_deterministic(b, learned[1]))
    if per == "round":
        d = _item_differences(a, b, higher, log).droplevel("item")
        return Replicates(d, "rounds", 0, 0, undefined, fixed)
    if all(fixed):
        d = _item_differences(_once_per_item(a), _once_per_item(b), higher, log)
        seeds = a.index.get_level_values("replicate").nunique()
        return Replicates(d, "images", seeds, len(d), undefined, fixed)
    if fixed[1]:
        b = _broadcast(_once_per_item(b), a)
    if fixed[0]:
        a = _broadcast(_once_per_item(a), b)
    per_image = _item_differences(a, b, higher, log)
    with np.errstate(invalid="ignore"):
        d = per_image.groupby(level="replicate").mean().fillna(0.0)  # +inf and -inf in one replicate: 0
    present = tuple(
        None if fixed[i] else {*table.index.get_level_values("replicate"), *lost[i]}
        for i, table in enumerate((a, b))
    )
    d = _with_lost_runs(d, lost, present, higher)
    images = per_image.index.get_level_values("item").nunique()
    return Replicates(d, "seeds", len(d), images, undefined, fixed)


def _lost_replicates(table: pd.DataFrame) -> set[str]:
    """The replicates whose run failed as a whole (module docstring)."""
    items = table.index.get_level_values("item")
    return set(table.index.get_level_values("replicate")[items == RUN_FAILED])


def _scored_items(table: pd.DataFrame) -> pd.DataFrame:
    return table[table.index.get_level_values("item") != RUN_FAILED]


def _with_lost_runs(
    d: pd.Series, lost: tuple[set[str], set[str]], present: tuple[set | None, set | None], higher: bool
) -> pd.Series:
    """`d` with each replicate whose run failed in one arm set to that arm's worst (-inf against a's loss
    when higher is better), 0 where both failed; only where the other arm has the replicate (`present`:
    None for a deterministic arm, which has every one)."""
    worst_for_a = -np.inf if higher else np.inf
    d = d.copy()
    for replicate in sorted(lost[0] | lost[1]):
        if not all(p is None or replicate in p for p in present):
            continue
        both = replicate in lost[0] and replicate in lost[1]
        d.loc[replicate] = 0.0 if both else (worst_for_a if replicate in lost[0] else -worst_for_a)
    d.index.name = "replicate"
    return d.sort_index()


def _broadcast(once: pd.DataFrame, other: pd.DataFrame) -> pd.DataFrame:
    """A deterministic arm's one score per item, repeated under each replicate of the other arm."""
    replicates = other.index.get_level_values("replicate").unique()
    parts = {r: once for r in replicates}
    if not parts:
        return other.iloc[0:0]
    return pd.concat(parts, names=["replicate"])
