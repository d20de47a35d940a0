"""The reproduction ledger: every claim of `conf/claims.yaml` with the status its logged runs give it.

For each claim (`src.report.claims`): the FINISHED MLflow runs of its study, pipeline or benchmark at the
first of its profiles that has any made at that profile's budget (the newest run per compared setting and
seed, as the reports keep them; runs whose overrides move a budget key are listed as not counted); a
check that the arms are matched (`src.report.matched_arms`: else **confounded**, naming the key); each
arm's scores per item, reduced to one difference per replicate (`src.report.replication`: training seeds
for learned arms, images for deterministic ones; a failed output is its arm's worst outcome); and the
status from `src.report.verdicts`, with the p-values of a study's tests adjusted together
(Benjamini-Hochberg, family = the claims read from one source at one profile). A claim without runs is
**not run**, with the reason and the command that produces them. `write_ledger` writes
`ledger.{md,csv}` and one CSV of replicate differences per claim, `write_ledger_page` `ledger.html`
(`src.report.ledger_page`).
"""

from __future__ import annotations

import logging
import math
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from src.errors import DataError
from src.report.claims import Claim
from src.report.collect import (
    artifact_csv,
    find_runs,
    keep_latest,
    param_column,
    per_image_rows,
    searches_cached,
)
from src.report.matched_arms import (
    HYDRA_JOB_TAG,
    canonical_value,
    derived_keys,
    first_confound,
    model_keys,
    off_profile_key,
    profile_keys,
)
from src.report.paired import item_means
from src.report.replication import REPLICATE, RUN_FAILED_COLUMN, Replicates, replicate_differences
from src.report.signed_rank import benjamini_hochberg
from src.report.tables import measured_on, run_costs
from src.report.verdicts import (
    CONFOUNDED,
    NOT_RUN,
    UNDERPOWERED,
    Verdict,
    agreement_verdict,
    better_verdict,
    comparable_verdict,
    not_worse_verdict,
)

log = logging.getLogger("nrbench.ledger")

#: The MLflow artifact of `python -m src.bench denoise --log`: one row per model and round.
BENCH_ROUNDS_ARTIFACT = "bench/rounds.csv"
#: Tasks whose output is found anew for every seed (the GP filter search): replicated by their seeds.
SEARCH_TASKS = ("filter_search",)
#: The LPIPS variant of a run's scores (src/eval/loop.py): "vgg16-random(seed=0)+lin-uniform" without weights.
LPIPS_VARIANT_TAG = "tags.nrbench.lpips_variant"
#: The evaluation's share of an item's frames whose output was undefined (per image), and its run metric.
UNDEFINED_COLUMN = {"image": "metrics.undefined", "run": "metrics.eval_undefined"}
NEEDS_REASONS = {
    "gpu": "needs a GPU (paper-scale runs)",
    "user_data": "needs the user's data (the scenes are not rendered here)",
}


@dataclass(frozen=True)
class LedgerSettings:
    """What the ledger needs besides the claims: the test level, every profile's name, the keys a profile
    file sets (`matched_arms.profile_keys`), groups of commits declared to be the same code, each model's
    own recipe keys (`matched_arms.model_keys`) and the budget keys a row prints (`ledger.budget_shown`)."""

    alpha: float = 0.05
    all_profiles: tuple[str, ...] = ()
    budget_keys: frozenset[str] = frozenset()
    equivalent_commits: tuple[tuple[str, ...], ...] = ()
    model_keys: Mapping[str, frozenset[str]] = field(default_factory=dict)
    budget_shown: tuple[str, ...] = ()
    # the profiles from the cheapest to the dearest (`ledger.profile_order`): the order of a claim's routes
    profile_order: tuple[str, ...] = ("smoke", "cpu", "paper", "thesis", "bako")


@dataclass(frozen=True)
class LedgerRow:
    """One claim's line in the ledger: its status and numbers, and what they rest on."""

    claim: Claim
    profile: str
    runs_from: str  # "study <name>", "pipeline" or "bench <name>"; "-" when not run
    verdict: Verdict
    runs: int
    commits: tuple[str, ...]
    fingerprints: tuple[str, ...]
    replicates: Replicates | None = None
    not_counted: str = ""  # runs at the profile left out, with the key that moved them off its budget
    run_ids: tuple[str, ...] = ()
    p_adjusted: float = math.nan
    family: str = ""
    arm_budget: str = ""  # budget keys on which the arms differ (declared or a model's own), per arm
    run_budget: str = ""  # the counted runs' values of `ledger.budget_shown`, beside the seed's budget
    names: tuple[str, str] = ("a", "b")  # the arms as the numbers name them
    # the counted runs' device cards (device, threads, precision) with run counts, then their median FLOPs,
    # GFLOP/s and peak memory (`run_costs`)
    measured_on: str = ""
    routes: str = ""  # the command at each of the claim's profiles, cheapest first (`routes`)


def matching(frame: pd.DataFrame, wanted: Mapping[str, str], prefix: str = "params.") -> pd.Series:
    """Rows of `frame` whose `<prefix><key>` equals each wanted value (a missing column matches nothing)."""
    mask = pd.Series(True, index=frame.index)
    for key, value in wanted.items():
        column = f"{prefix}{key}"
        if column not in frame:
            return pd.Series(False, index=frame.index)
        mask &= frame[column].map(canonical_value) == canonical_value(value)
    return mask


def _source_filter(kind: str, name: str) -> tuple[str | None, dict[str, str]]:
    """The MLflow filter string and tags that select one kind of runs: a study's jobs, the DVC pipeline's
    runs (its tag; the claim's experiment says which task), or a bench's runs."""
    if kind == "study":
        return f"params.`report.name` = 'sweeps/{name}'", {}
    if kind == "pipeline":
        return None, {"nrbench.group": "dvc"}
    return f"params.bench = '{name}'", {}


def _arm_keys(claim: Claim) -> list[str]:
    rule = claim.rule
    keys = [*rule.a, *rule.b, *claim.where, *(k for c in rule.published for k in [*c.arm, *c.where])]
    return list(dict.fromkeys([*keys, "task.scene"]))


def claim_runs(claim: Claim, source: tuple[str, str], profile: str, status: str = "FINISHED") -> pd.DataFrame:
    """The claim's FINISHED (or FAILED) runs from `source` at `profile` that match its `where`: the newest
    per compared setting and seed (a bench: its newest run). Empty when there are none (or no
    experiment)."""
    where, tags = _source_filter(*source)
    report_cfg = {
        "experiment": claim.experiment,
        "tags": {**tags, "nrbench.profile": profile},
        "filter": where,
        "status": status,
    }
    try:
        runs = find_runs(report_cfg, level=logging.DEBUG)  # one claim, source and profile of many: quietly
    except DataError as err:
        log.debug("ledger: %s: no runs at %s (%s)", claim.id, profile, err)
        return pd.DataFrame()
    # `where` before keeping the newest, so that a newer run it leaves out cannot hide an older one it
    # keeps. A bench run has no axes and no seed: the newest per (nothing) is its newest run.
    runs = runs[matching(runs, claim.where)]
    return keep_latest(runs, [] if claim.is_bench else _arm_keys(claim))


def failed_runs(claim: Claim, source: tuple[str, str], profile: str, finished: pd.DataFrame) -> pd.DataFrame:
    """The claim's runs that ended in an error (MLflow status FAILED) for a compared setting and seed that
    has no finished run among `finished`: a training that crashed or diverged is its arm's loss on that
    replicate, never a replicate left out (a requeued job that finished later replaces it). A bench has
    no seeds: none."""
    if claim.is_bench:
        return pd.DataFrame()
    failed = _compared_runs(claim, claim_runs(claim, source, profile, status="FAILED"))
    if failed.empty:
        return failed
    keys = [param_column(a) for a in [*_arm_keys(claim), "seed"]]

    def key(frame: pd.DataFrame) -> pd.Series:
        columns = frame.reindex(columns=keys).map(canonical_value)
        return columns.apply(lambda row: "|".join(row), axis=1)

    done = set(key(finished)) if not finished.empty else set()
    return failed[~key(failed).isin(done)]


def _bench_rounds(runs: pd.DataFrame) -> pd.DataFrame:
    """The rounds table of the (newest) bench run, its columns (model, round, seconds) as is; empty when
    the run has none."""
    with tempfile.TemporaryDirectory() as tmp:
        rounds = artifact_csv(runs["run_id"].iloc[-1], BENCH_ROUNDS_ARTIFACT, tmp)
    return pd.DataFrame() if rounds is None else rounds


def item_scores(
    claim: Claim, runs: pd.DataFrame, failed: pd.DataFrame | None = None
) -> tuple[pd.DataFrame, str]:
    """(scores, the arm-key prefix): one row per scored item of every run, with its value in column
    `value`, `failed` where the evaluation counted the item's output undefined, and what selects an arm
    (`params.*`, or a bench table's own columns). `failed`: runs that ended in an error (`failed_runs`),
    one row each, marked in `replication.RUN_FAILED_COLUMN`."""
    failed = pd.DataFrame() if failed is None else failed
    if claim.per == "round":
        rounds = _bench_rounds(runs)
        if rounds.empty or claim.metric not in rounds:
            return pd.DataFrame(), ""
        return rounds.assign(value=rounds[claim.metric]), ""
    if claim.per == "image":
        scored = per_image_rows(runs, required=claim.metric)
    else:
        column = f"metrics.{claim.metric}"
        failed_output = _failed(runs, "run", claim.metric)
        scored = runs[runs[column].notna() | failed_output] if column in runs else runs.iloc[0:0]
    if not failed.empty:
        # One row per failed run: no item of it was scored (replication.RUN_FAILED).
        lost = failed[[c for c in failed.columns if c.startswith("params.") or c == "run_id"]]
        scored = pd.concat([scored, lost.assign(**{RUN_FAILED_COLUMN: True})], ignore_index=True)
    if scored.empty:
        return scored, "params."
    return scored.assign(
        value=scored.get(f"metrics.{claim.metric}", np.nan), failed=_failed(scored, claim.per, claim.metric)
    ), "params."


def _failed(scores: pd.DataFrame, per: str, metric: str) -> pd.Series:
    """Items whose output was undefined (a share of frames > 0), and failed runs: their arm's worst
    outcome. Per run, an undefined held-out output fails only the evaluation's scores (`eval_*`): a
    search's fitness or a training's time is defined whatever the held-out images gave."""
    column = UNDEFINED_COLUMN[per]
    lost = scores[RUN_FAILED_COLUMN].fillna(False).astype(bool) if RUN_FAILED_COLUMN in scores else False
    if column not in scores or (per == "run" and not metric.startswith("eval_")):
        return pd.Series(False, index=scores.index) | lost
    return (pd.to_numeric(scores[column], errors="coerce").fillna(0.0) > 0) | lost


def arm_values(scores: pd.DataFrame, arm: Mapping[str, str], prefix: str, item: Sequence[str]) -> pd.Series:
    """An arm's scores, one per item (the mean where it has one item twice), non-finite ones dropped: an
    agreement case's values."""
    part = scores[matching(scores, arm, prefix)] if not scores.empty else scores
    return pd.Series(dtype=float) if part.empty else item_means(part, "value", item)


def _scored_by(scores: pd.DataFrame, metric: str) -> pd.DataFrame:
    """`scores` with `value` from another metric of the same runs or images (`Rule.b_metric`); no rows
    when they do not have it. A baseline scored beside the method does not share the method's failures."""
    column = f"metrics.{metric}"
    if column not in scores:
        return scores.iloc[0:0]
    return scores.assign(value=scores[column], failed=False)


def _label(arm: Mapping[str, str]) -> str:
    """An arm as the ledger names it: a model by its name, any other setting as `last_key=value`."""
    return ", ".join(
        v if k in ("model.name", "model") else f"{k.rsplit('.', 1)[-1]}={v}" for k, v in arm.items()
    )


def arm_learned(part: pd.DataFrame) -> bool | None:
    """Whether an arm's output depends on its training seed: its `model.learned`, or a search task's run
    (the filter search's `gp_filter` is not trained, but the expression it finds is the seed's). None
    when the runs do not say, or disagree: the scores then decide (`replication.is_deterministic`)."""
    tasks = {str(v) for v in part.get("params.task.name", pd.Series(dtype=str)).dropna()}
    if tasks and tasks <= set(SEARCH_TASKS):
        return True
    column = "params.model.learned"
    if column not in part or part.empty:
        return None
    values = {str(v).strip().lower() for v in part[column].dropna()}
    return {"true": True, "false": False}.get(values.pop()) if len(values) == 1 else None


def _agreement(claim: Claim, scores: pd.DataFrame, prefix: str) -> Verdict:
    """Each published case's values: one per replicate (the mean over its items)."""
    cases = []
    for case in claim.rule.published:
        values = arm_values(scores, {**case.arm, **case.where}, prefix, REPLICATE)
        cases.append((_label({**case.arm, **case.where}), values if len(values) else None, case.value))
    return agreement_verdict(cases, claim.rule.tolerance)


def _replicates(claim: Claim, scores: pd.DataFrame, prefix: str) -> tuple[Replicates, tuple[str, str]] | str:
    """The claim's per-replicate differences and the arms' names, or why there are none."""
    rule = claim.rule
    b_scores = scores if rule.b_metric is None else _scored_by(scores, rule.b_metric)
    a = scores[matching(scores, rule.a, prefix)] if not scores.empty else scores
    b = b_scores[matching(b_scores, rule.b, prefix)] if not b_scores.empty else b_scores
    names = (_label(rule.a), _label(rule.b) + (f" ({rule.b_metric})" if rule.b_metric else ""))
    if a.empty or b.empty:
        return f"no {claim.metric} scores for arm {names[0] if a.empty else names[1]}"
    # A baseline scored beside the method (b_metric) is not the run's model: whether it is deterministic
    # shows in its scores.
    learned = (arm_learned(a), arm_learned(b)) if rule.b_metric is None else (arm_learned(a), None)
    return replicate_differences(a, b, claim.per, claim.higher, claim.log, learned), names


def _judge(claim: Claim, replicates: Replicates, names: tuple[str, str], alpha: float, p_adjusted=None):
    """The status of a better, comparable or not-worse claim from its replicates (`src.report.verdicts`)."""
    unit, nesting, tolerance = replicates.unit, _nesting(replicates), claim.rule.tolerance
    if claim.rule.kind == "comparable":
        return comparable_verdict(replicates.difference, names, claim.log, tolerance, alpha, unit, nesting)
    advantage = replicates.difference if claim.higher else -replicates.difference
    if claim.rule.kind == "not_worse":
        return not_worse_verdict(advantage, names, claim.log, tolerance, alpha, unit, nesting)
    return better_verdict(advantage, names, claim.log, claim.rule.size, alpha, unit, p_adjusted, nesting)


def _nesting(replicates: Replicates) -> str:
    if replicates.unit == "seeds":
        return f" ({replicates.images} item(s) nested in each)"
    if replicates.unit == "images":
        return f" (deterministic arms: each image once, though scored under {replicates.seeds} seed(s))"
    return ""


def _not_run(claim: Claim, other_profiles: list[str], not_counted: list[str], to_run: str) -> Verdict:
    reasons = [NEEDS_REASONS[claim.needs]] if claim.needs else []
    reasons.append(f"no runs at {' or '.join(claim.profiles)}")
    if other_profiles:
        reasons.append(f"runs at {', '.join(other_profiles)} only, where it is not meaningful")
    reasons += not_counted
    return Verdict(NOT_RUN, f"{'; '.join(reasons)}; to run (cheapest first): {to_run}")


def duration_text(seconds: float) -> str:
    """A run time as a reader wants it: "45 s", "41 min", "3.2 h"."""
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 90 * 60:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def run_time(runs: pd.DataFrame) -> str:
    """What the runs took: the sum of their wall times (start to end: a study's jobs one after another)
    with the machines they ran on and their counts; "not measured in this store" without runs."""
    if runs.empty or "end_time" not in runs or "start_time" not in runs:
        return "not measured in this store"
    seconds = (pd.to_datetime(runs["end_time"]) - pd.to_datetime(runs["start_time"])).dt.total_seconds()
    seconds = seconds.dropna()
    if seconds.empty:
        return "not measured in this store"
    return f"measured: {duration_text(seconds.sum())} of run time on {measured_on(runs)}"


def routes(claim: Claim, settings: LedgerSettings) -> str:
    """The command that makes the claim's runs at each of its profiles (only those where it means
    something), cheapest first by `settings.profile_order`, each with the time its runs took in this
    store where it has any: "cpu: python -m src.run -m +sweep=x profile=cpu (measured: 41 min of run
    time on AMD EPYC, 2 threads, fp32 (12 runs)); paper: ... (not measured in this store)"."""
    order = settings.profile_order
    ranked = sorted(claim.profiles, key=lambda p: order.index(p) if p in order else len(order))
    parts = []
    for profile in ranked:
        runs = _compared_runs(claim, claim_runs(claim, claim.sources[0], profile))
        parts.append(f"{profile}: {claim.command(profile)} ({run_time(runs)})")
    return "; ".join(parts)


def _provenance(runs: pd.DataFrame, column: str) -> tuple[str, ...]:
    if column not in runs:
        return ()
    return tuple(sorted({str(v)[:12] for v in runs[column].dropna()}))


def _arms(claim: Claim) -> list[dict[str, str]]:
    rule = claim.rule
    return [rule.a, rule.b] if rule.kind != "agreement" else [{**c.arm, **c.where} for c in rule.published]


def _compared_runs(claim: Claim, runs: pd.DataFrame) -> pd.DataFrame:
    """The runs of the arms the claim compares (the others of its study say nothing about it); a bench's
    arms are rows of its rounds table, so its run is kept whole."""
    if claim.is_bench or runs.empty:
        return runs
    mask = pd.Series(False, index=runs.index)
    for arm in _arms(claim):
        mask |= matching(runs, arm)
    return runs[mask]


def _at_budget(claim: Claim, runs: pd.DataFrame, settings: LedgerSettings) -> tuple[pd.DataFrame, str]:
    """The runs made at their profile's budget (and, for an LPIPS claim, with trained LPIPS weights), and a
    note on the others: the key that moved each off the budget, or the LPIPS variant."""
    notes, keep = [], pd.Series(True, index=runs.index)
    if claim.metric.endswith("lpips") and LPIPS_VARIANT_TAG in runs:
        # A random VGG trunk (or uniform linear weights) scores on another scale than published LPIPS.
        untrained = runs[LPIPS_VARIANT_TAG].astype(str).str.contains("random|uniform", regex=True)
        if untrained.any():
            notes.append(f"{int(untrained.sum())} run(s) not counted: LPIPS without the trained weights")
        keep &= ~untrained
    if not claim.is_bench and HYDRA_JOB_TAG in runs and settings.budget_keys:
        allowed = [*_arm_keys(claim), *claim.rule.ratio]
        keys = runs[HYDRA_JOB_TAG].map(lambda job: off_profile_key(job, settings.budget_keys, allowed))
        off = keys[(keys != "") & keep]
        if not off.empty:
            moved = ", ".join(sorted(set(off)))
            notes.append(f"{len(off)} run(s) not counted, off the profile's budget ({moved} overridden)")
        keep &= keys == ""
    return runs[keep], "; ".join(notes)


def _confound(claim: Claim, runs: pd.DataFrame, settings: LedgerSettings) -> str | None:
    """The first key on which the compared arms' runs differ besides the arms (None when matched). A model
    an arm picks brings its own recipe keys (its model_profile and model_task_profile files). An agreement
    compares each case with its published value, so each case's runs must match among themselves."""
    rule = claim.rule
    keys = _arm_keys(claim)
    keys += derived_keys(keys)
    for arm in _arms(claim):
        keys += sorted(settings.model_keys.get(arm.get("model.name", ""), ()))
    if rule.kind == "agreement" and not claim.is_bench:
        for arm in _arms(claim):
            found = first_confound(
                runs[matching(runs, arm)], runs.iloc[0:0], keys, {}, settings.equivalent_commits
            )
            if found:
                return f"{_label(arm)}: {found}"
        return None
    if claim.is_bench or rule.b_metric is not None:
        return first_confound(runs, runs.iloc[0:0], keys, {}, settings.equivalent_commits)
    a, b = runs[matching(runs, rule.a)], runs[matching(runs, rule.b)]
    return first_confound(a, b, keys, rule.ratio, settings.equivalent_commits)


def _runs_from(source: tuple[str, str]) -> str:
    return "pipeline" if source[0] == "pipeline" else " ".join(source)


def _arm_budget(claim: Claim, runs: pd.DataFrame, settings: LedgerSettings) -> str:
    """The budget keys that differ between the arms as each ran them: those the claim declares
    (`rule.ratio`) and the budget keys of a model's own recipe ("task.train.epochs: kpcn 8; dpcn 16")."""
    if claim.rule.kind == "agreement":
        return ""
    owned = {
        key
        for arm in (claim.rule.a, claim.rule.b)
        for key in settings.model_keys.get(arm.get("model.name", ""), ())
        if key in settings.budget_keys and not key.startswith("model.")  # a model's size is its own
    }
    parts = []
    for key in sorted({*claim.rule.ratio, *owned}):
        column = f"params.{key}"
        if column not in runs:
            continue
        values = [
            sorted(set(runs.loc[matching(runs, arm), column].astype(str)))
            for arm in (claim.rule.a, claim.rule.b)
        ]
        if key in claim.rule.ratio or values[0] != values[1]:
            shown = [
                f"{_label(arm)} {', '.join(v)}"
                for arm, v in zip((claim.rule.a, claim.rule.b), values, strict=True)
            ]
            parts.append(f"{key}: {'; '.join(shown)}")
    return " | ".join(parts)


def _too_few_draws(claim: Claim, runs: pd.DataFrame) -> str:
    """Why arm b's runs hold too few distinct values of a `rule.b_distinct` key ("" when enough): a
    baseline drawn at random once is one draw, however many seeds trained on it."""
    b = runs[matching(runs, claim.rule.b)]
    for key, needed in claim.rule.b_distinct.items():
        column = f"params.{key}"
        found = b[column].map(canonical_value).nunique() if column in b else 0
        if found < needed:
            return (
                f"arm {_label(claim.rule.b)} holds {found} distinct {key} over {len(b)} run(s); the claim "
                f"needs {needed} or more (rule.b_distinct): one draw stands for no distribution of draws"
            )
    return ""


def run_budget(runs: pd.DataFrame, keys: Sequence[str]) -> str:
    """The runs' values of the budget `keys` they logged ("task.train.epochs 8, 16; task.train.batch_size
    16"), every distinct value of a key in sorted order, to print beside the seed's budget."""
    parts = []
    for key in keys:
        column = f"params.{key}"
        if column in runs:
            logged = runs[column].dropna().astype(str)
            values = sorted(set(logged[logged != "None"]), key=_numeric_first)  # MLflow logs null as "None"
            if values:
                parts.append(f"{key} {', '.join(values)}")
    return "; ".join(parts)


def _numeric_first(value: str) -> tuple[int, float, str]:
    try:
        return (0, float(value), value)
    except ValueError:
        return (1, 0.0, value)


def _row(
    claim: Claim,
    profile: str,
    source,
    runs: pd.DataFrame,
    settings: LedgerSettings,
    note: str,
    failed: pd.DataFrame | None = None,
):
    """The ledger row of the claim's counted runs at `profile` from `source`, and of its failed runs."""
    failed = pd.DataFrame() if failed is None else failed
    ids = [*runs.get("run_id", []), *failed.get("run_id", [])]
    common = dict(
        claim=claim,
        profile=profile,
        runs_from=_runs_from(source),
        runs=len(runs),
        commits=_provenance(runs, "tags.nrbench.git_commit"),
        fingerprints=_provenance(runs, "tags.nrbench.data_fingerprint"),
        not_counted=note,
        run_ids=tuple(str(r) for r in ids),  # the failed runs' too: they count as losses
        arm_budget=_arm_budget(claim, runs, settings) if not claim.is_bench else "",
        run_budget=run_budget(runs, settings.budget_shown),
        measured_on=f"{measured_on(runs)}; {run_costs(runs)}" if len(runs) else "",
        routes=routes(claim, settings),
    )
    confound = _confound(claim, runs, settings)
    if confound:
        return LedgerRow(
            verdict=Verdict(CONFOUNDED, f"the compared runs are not matched: {confound}"), **common
        )
    scores, prefix = item_scores(claim, runs, failed)
    if claim.rule.kind == "agreement":
        return LedgerRow(verdict=_agreement(claim, scores, prefix), **common)
    draws = _too_few_draws(claim, runs)
    if draws:
        return LedgerRow(verdict=Verdict(UNDERPOWERED, draws), **common)
    prepared = _replicates(claim, scores, prefix)
    if isinstance(prepared, str):
        return LedgerRow(verdict=Verdict(NOT_RUN, prepared), **common)
    replicates, names = prepared
    verdict = _judge(claim, replicates, names, settings.alpha)
    return LedgerRow(verdict=verdict, replicates=replicates, names=names, **common)


def evaluate_claim(claim: Claim, settings: LedgerSettings | float = LedgerSettings()) -> LedgerRow:
    """The claim's ledger row: its status at the first of its profiles with runs at that profile's
    budget, from the first of its sources with such runs there (module docstring). A bare number is
    taken as the test level."""
    if not isinstance(settings, LedgerSettings):
        settings = LedgerSettings(alpha=float(settings))
    notes: list[str] = []
    for profile in claim.profiles:
        for source in claim.sources:
            runs = _compared_runs(claim, claim_runs(claim, source, profile))
            if runs.empty:
                continue
            counted, note = _at_budget(claim, runs, settings)
            if counted.empty:
                notes.append(f"at {profile}: {note}")
                continue
            failed, _ = _at_budget(claim, failed_runs(claim, source, profile, runs), settings)
            return _row(claim, profile, source, counted, settings, note, failed)
    others = [
        p
        for p in settings.all_profiles
        if p not in claim.profiles
        and any(not _compared_runs(claim, claim_runs(claim, s, p)).empty for s in claim.sources)
    ]
    to_run = routes(claim, settings)
    return LedgerRow(claim, "-", "-", _not_run(claim, others, notes, to_run), 0, (), (), routes=to_run)


def adjust_families(rows: Sequence[LedgerRow], alpha: float) -> list[LedgerRow]:
    """The rows with each `better` claim's p adjusted within its family (the claims read from one source
    at one profile) by Benjamini-Hochberg, and its status judged on the adjusted p. Rows without a test
    (underpowered, confounded, not run, comparable, agreement) are left as they are."""
    tested = [
        i
        for i, r in enumerate(rows)
        if r.replicates is not None
        and r.claim.rule.kind == "better"
        and math.isfinite(r.verdict.p_value)
        and r.claim.tallied
        and r.verdict.status != UNDERPOWERED
    ]
    out = list(rows)
    families: dict[str, list[int]] = {}
    for i in tested:
        families.setdefault(f"{rows[i].runs_from} at {rows[i].profile}", []).append(i)
    for family, members in families.items():
        adjusted = benjamini_hochberg([rows[i].verdict.p_value for i in members])
        for i, p in zip(members, adjusted, strict=True):
            row = rows[i]
            verdict = _judge(row.claim, row.replicates, row.names, alpha, p_adjusted=float(p))
            out[i] = replace(
                row, verdict=verdict, p_adjusted=float(p), family=f"{family} ({len(members)} tests)"
            )
    return out


def settings_from(cfg: Any, claims_path: Path) -> LedgerSettings:
    """The ledger's settings from the run config (`ledger.*`) and the conf folder beside the claims."""
    conf_dir = claims_path.parent
    groups = OmegaConf.select(cfg, "ledger.equivalent_commits", default=None) or []
    return LedgerSettings(
        alpha=float(cfg.ledger.alpha),  # in (0, 1): the run schema (src/schema/run.py) checked it
        all_profiles=tuple(sorted(p.stem for p in (conf_dir / "profile").glob("*.yaml"))),
        budget_keys=profile_keys(conf_dir),
        equivalent_commits=tuple(tuple(str(c) for c in group) for group in groups),
        model_keys=model_keys(conf_dir),
        budget_shown=tuple(str(k) for k in OmegaConf.select(cfg, "ledger.budget_shown", default=None) or ()),
        profile_order=tuple(
            str(p)
            for p in OmegaConf.select(cfg, "ledger.profile_order", default=None)
            or LedgerSettings.profile_order
        ),
    )


def build_ledger(cfg: Any) -> dict[str, Any]:
    """Evaluate every claim of `ledger.claims` against the runs of `tracking.uri` and write the ledger
    under `ledger.out_dir`; returns the paths written and the status of each claim."""
    from src.provenance import git_commit
    from src.report.claims import load_claims
    from src.report.ledger_page import ledger_frame, status_counts, write_ledger, write_ledger_page

    claims_path = Path(str(cfg.ledger.claims))
    claims = load_claims(claims_path)
    settings = settings_from(cfg, claims_path)
    mlflow.set_tracking_uri(str(cfg.tracking.uri))
    with searches_cached():  # the store does not change while the claims read it
        rows = adjust_families([evaluate_claim(claim, settings) for claim in claims], settings.alpha)
    frame = ledger_frame(rows)
    subtitle = (
        f"Each status is computed from the FINISHED runs in the tracking store by nrbench at commit "
        f"{git_commit() or 'unknown'} (claims: {claims_path.name}; Hodges-Lehmann shifts with signed-rank "
        f"tests and {1 - settings.alpha:.0%} intervals over replicates, Benjamini-Hochberg within each "
        "source at a profile). Statuses: reproduced, direction only (the sign holds, the interval excludes "
        "the published size), not reproduced, not distinguishable (the interval contains 0), underpowered "
        "(too few replicates to decide), confounded (the arms' runs differ in more than the arm), not run "
        "(with the reason). The headline counts the seeds' findings and readings."
    )
    out_dir = Path(str(cfg.ledger.out_dir))
    paths = write_ledger(frame, out_dir, subtitle, rows)
    paths.update(_record(cfg, frame, rows, paths))
    committed = OmegaConf.select(cfg, "report.committed_ledger", default=None)
    committed = Path(str(committed)) if committed else None
    paths["html"] = write_ledger_page(out_dir, committed)  # after _record: its label reads the history
    if OmegaConf.select(cfg, "report.site", default=True):
        from src.report.site import refresh_site

        refresh_site(out_dir, committed)  # the site's index shows the ledger's findings and what changed
    return {
        "paths": paths,
        "statuses": dict(zip(frame["claim"], frame["status"], strict=True)),
        "counts": status_counts(frame),
    }


def _record(cfg: Any, frame: pd.DataFrame, rows: Sequence[LedgerRow], paths: dict[str, Path]) -> dict:
    """Append this write to `<out_dir>/ledger_history.csv` and, with `ledger.snapshot`, write the committed
    snapshot there (`src.report.ledger_history`); returns the paths written."""
    from datetime import UTC, datetime

    from src.provenance import git_commit
    from src.report.ledger_history import append_history, history_lines, store_fingerprint, write_snapshot

    written = datetime.now(UTC).strftime("%Y-%m-%d %H:%M:%S UTC")
    full = git_commit() or "unknown"
    commit = full[:12] + ("+dirty" if full.endswith("+dirty") else "")  # as the rows' commits are shown
    run_ids = [run_id for row in rows for run_id in row.run_ids]
    store = store_fingerprint(run_ids)
    lines = history_lines(frame, written, commit, store)
    out = {"history": Path(str(cfg.ledger.out_dir)) / "ledger_history.csv"}
    append_history(out["history"], lines)
    folder = OmegaConf.select(cfg, "ledger.snapshot", default=None)
    if folder:
        folder = Path(str(folder))
        header = (
            f"ledger written {written} by nrbench at commit {commit} from a store of {len(set(run_ids))} "
            f"counted runs (store fingerprint {store})"
        )
        csv_text, md_text = paths["csv"].read_text(), paths["md"].read_text()
        items = [
            paths["csv"].parent / "items" / f"{r.claim.id}.csv" for r in rows if r.replicates is not None
        ]
        out["snapshot"] = write_snapshot(folder, header, csv_text, md_text, lines, items)[0]
    return out


def ledger_line(summary: dict[str, Any]) -> str:
    """What the stage prints: where the ledger is and its status counts."""
    return f"ledger: {summary['counts']} -> {summary['paths']['md']}"
