"""The reproduction ledger: every claim of `conf/claims.yaml` with the status its logged runs give it.

For each claim (`src.report.claims`): the FINISHED MLflow runs of its study, pipeline or benchmark at the
first of its profiles that has any (the newest run per compared setting and seed, as the reports keep
them); each arm's scores per item (held-out image, seed or benchmark round); the status from
`src.report.verdicts`. A claim without runs is **not run**, with the reason (it needs a GPU or the
user's data, or its study has not run at a profile where it means something) and the command that
produces them. Every status carries the profile, the git commits and the data fingerprints of the runs
behind it. `write_ledger` writes `ledger.{md,html,csv}` (`src.report.ledger_page`).
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import mlflow
import pandas as pd
from omegaconf import OmegaConf

from src.errors import DataError
from src.report.claims import Claim
from src.report.collect import artifact_csv, find_runs, keep_latest, per_image_rows
from src.report.tables import item_means
from src.report.verdicts import (
    NOT_RUN,
    Verdict,
    agreement_verdict,
    better_verdict,
    comparable_verdict,
)

log = logging.getLogger("nrbench.ledger")

#: The MLflow artifact of `python -m src.bench denoise --log`: one row per model and round.
BENCH_ROUNDS_ARTIFACT = "bench/rounds.csv"
#: What identifies one item of a per-image score: the seed and the held-out image (a denoising image is
#: a scene at a sample count, a NeRF one a view).
IMAGE_ITEM = ("params.seed", "scene", "spp", "view")
#: One item of a per-run score: the seed (and the scene, for studies that sweep scenes).
RUN_ITEM = ("params.seed", "params.task.scene")
NEEDS_REASONS = {
    "gpu": "needs a GPU (paper-scale runs)",
    "user_data": "needs the user's data (the scenes are not rendered here)",
}


@dataclass(frozen=True)
class LedgerRow:
    """One claim's line in the ledger."""

    claim: Claim
    profile: str
    runs_from: str  # "study <name>", "pipeline" or "bench <name>"; "-" when not run
    verdict: Verdict
    runs: int
    commits: tuple[str, ...]
    fingerprints: tuple[str, ...]


def _canonical(value: Any) -> str:
    """A param value as compared: booleans and numbers by value ("True" = "true", "0.0" = "0"), the rest
    as text (MLflow stores every param as a string)."""
    text = str(value).strip()
    if text.lower() in ("true", "false"):
        return text.lower()
    try:
        return repr(float(text))
    except ValueError:
        return text


def matching(frame: pd.DataFrame, wanted: Mapping[str, str], prefix: str = "params.") -> pd.Series:
    """Rows of `frame` whose `<prefix><key>` equals each wanted value (a missing column matches nothing)."""
    mask = pd.Series(True, index=frame.index)
    for key, value in wanted.items():
        column = f"{prefix}{key}"
        if column not in frame:
            return pd.Series(False, index=frame.index)
        mask &= frame[column].map(_canonical) == _canonical(value)
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


def claim_runs(claim: Claim, source: tuple[str, str], profile: str) -> pd.DataFrame:
    """The claim's FINISHED runs from `source` at `profile` that match its `where`: the newest per
    compared setting and seed (a bench: its newest run). Empty when there are none (or no experiment)."""
    where, tags = _source_filter(*source)
    report_cfg = {
        "experiment": claim.experiment,
        "tags": {**tags, "nrbench.profile": profile},
        "filter": where,
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


def _bench_rounds(runs: pd.DataFrame) -> pd.DataFrame:
    """The rounds table of the (newest) bench run, its columns (model, round, seconds) as is; empty when
    the run has none."""
    with tempfile.TemporaryDirectory() as tmp:
        rounds = artifact_csv(runs["run_id"].iloc[-1], BENCH_ROUNDS_ARTIFACT, tmp)
    return pd.DataFrame() if rounds is None else rounds


def item_scores(claim: Claim, runs: pd.DataFrame) -> tuple[pd.DataFrame, str, list[str]]:
    """(scores, the arm-key prefix, the item columns): one row per scored item of every run, with its
    value in column `value` and what selects an arm (`params.*`, or a bench table's own columns)."""
    if claim.per == "round":
        rounds = _bench_rounds(runs)
        if rounds.empty or claim.metric not in rounds:
            return pd.DataFrame(), "", []
        return rounds.assign(value=rounds[claim.metric]), "", ["round"]
    if claim.per == "image":
        images = per_image_rows(runs, required=claim.metric)
        if images.empty:
            return images, "params.", []
        return images.assign(value=images[f"metrics.{claim.metric}"]), "params.", list(IMAGE_ITEM)
    column = f"metrics.{claim.metric}"
    scored = runs[runs[column].notna()] if column in runs else runs.iloc[0:0]
    return scored.assign(value=scored.get(column)), "params.", list(RUN_ITEM)


def arm_values(scores: pd.DataFrame, arm: Mapping[str, str], prefix: str, item: list[str]) -> pd.Series:
    """An arm's scores, one per item (the mean where it has one item twice), non-finite ones dropped."""
    part = scores[matching(scores, arm, prefix)] if not scores.empty else scores
    return pd.Series(dtype=float) if part.empty else item_means(part, "value", item)


def _scored_by(scores: pd.DataFrame, metric: str) -> pd.DataFrame:
    """`scores` with `value` from another metric of the same runs or images (`Rule.b_metric`); no rows
    when they do not have it."""
    column = f"metrics.{metric}"
    return scores.assign(value=scores[column]) if column in scores else scores.iloc[0:0]


def _label(arm: Mapping[str, str]) -> str:
    """An arm as the ledger names it: a model by its name, any other setting as `last_key=value`."""
    return ", ".join(
        v if k in ("model.name", "model") else f"{k.rsplit('.', 1)[-1]}={v}" for k, v in arm.items()
    )


def _verdict(claim: Claim, scores: pd.DataFrame, prefix: str, item: list[str], alpha: float) -> Verdict:
    rule = claim.rule
    if rule.kind == "agreement":
        cases = []
        for case in rule.published:
            values = arm_values(scores, {**case.arm, **case.where}, prefix, item)
            label = _label({**case.arm, **case.where})
            cases.append((label, values if len(values) else None, case.value))
        return agreement_verdict(cases, rule.tolerance)
    b_scores = scores if rule.b_metric is None else _scored_by(scores, rule.b_metric)
    a, b = arm_values(scores, rule.a, prefix, item), arm_values(b_scores, rule.b, prefix, item)
    names = (_label(rule.a), _label(rule.b) + (f" ({rule.b_metric})" if rule.b_metric else ""))
    if a.empty or b.empty:
        missing = names[0] if a.empty else names[1]
        return Verdict(NOT_RUN, f"no {claim.metric} scores for arm {missing}")
    if rule.kind == "comparable":
        return comparable_verdict(a, b, names, claim.log, rule.tolerance)
    return better_verdict(a, b, names, claim.higher, claim.log, rule.size, alpha)


def _not_run(claim: Claim, other_profiles: list[str]) -> Verdict:
    reasons = [NEEDS_REASONS[claim.needs]] if claim.needs else []
    reasons.append(f"no runs at {' or '.join(claim.profiles)}")
    if other_profiles:
        reasons.append(f"runs at {', '.join(other_profiles)} only, where it is not meaningful")
    return Verdict(NOT_RUN, f"{'; '.join(reasons)}; to run: {claim.command(claim.profiles[0])}")


def _provenance(runs: pd.DataFrame, column: str) -> tuple[str, ...]:
    if column not in runs:
        return ()
    return tuple(sorted({str(v)[:12] for v in runs[column].dropna()}))


def _compared_runs(claim: Claim, runs: pd.DataFrame) -> pd.DataFrame:
    """The runs of the arms the claim compares (the others of its study say nothing about it); a bench's
    arms are rows of its rounds table, so its run is kept whole."""
    if claim.is_bench:
        return runs
    rule = claim.rule
    arms = [rule.a, rule.b] if rule.kind != "agreement" else [{**c.arm, **c.where} for c in rule.published]
    mask = pd.Series(False, index=runs.index)
    for arm in arms:
        mask |= matching(runs, arm)
    return runs[mask]


def _runs_from(source: tuple[str, str]) -> str:
    return "pipeline" if source[0] == "pipeline" else " ".join(source)


def evaluate_claim(claim: Claim, alpha: float, all_profiles: tuple[str, ...] = ()) -> LedgerRow:
    """The claim's ledger row: its status at the first of its profiles with runs, from the first of its
    sources with runs there (a study's seeds before the pipeline's one run per model; module docstring)."""
    for profile in claim.profiles:
        for source in claim.sources:
            runs = _compared_runs(claim, claim_runs(claim, source, profile))
            if runs.empty:
                continue
            scores, prefix, item = item_scores(claim, runs)
            return LedgerRow(
                claim,
                profile,
                _runs_from(source),
                _verdict(claim, scores, prefix, item, alpha),
                len(runs),
                _provenance(runs, "tags.nrbench.git_commit"),
                _provenance(runs, "tags.nrbench.data_fingerprint"),
            )
    others = [
        p
        for p in all_profiles
        if p not in claim.profiles
        and any(not _compared_runs(claim, claim_runs(claim, s, p)).empty for s in claim.sources)
    ]
    return LedgerRow(claim, "-", "-", _not_run(claim, others), 0, (), ())


def build_ledger(cfg: Any) -> dict[str, Any]:
    """Evaluate every claim of `ledger.claims` against the runs of `tracking.uri` and write the ledger
    under `ledger.out_dir`; returns the paths written and the status of each claim."""
    from pathlib import Path

    from src.provenance import git_commit
    from src.report.claims import load_claims
    from src.report.ledger_page import ledger_frame, status_counts, write_ledger

    alpha = float(cfg.ledger.alpha)  # in (0, 1): the run schema (src/schema/run.py) checked it
    claims_path = Path(str(cfg.ledger.claims))
    claims = load_claims(claims_path)
    mlflow.set_tracking_uri(str(cfg.tracking.uri))
    all_profiles = tuple(sorted(p.stem for p in (claims_path.parent / "profile").glob("*.yaml")))
    rows = [evaluate_claim(claim, alpha, all_profiles) for claim in claims]
    frame = ledger_frame(rows)
    subtitle = (
        f"Each status is computed from the FINISHED runs in {mlflow.get_tracking_uri()} by nrbench at "
        f"commit {git_commit() or 'unknown'} (claims: {claims_path.name}; paired tests at alpha {alpha:g}). "
        "Statuses: reproduced, direction only (the sign holds, the size does not), not reproduced, "
        "not distinguishable (inside the spread of seeds and items), not run (with the reason)."
    )
    paths = write_ledger(frame, Path(str(cfg.ledger.out_dir)), subtitle)
    if OmegaConf.select(cfg, "report.site", default=True):
        from src.report.site import refresh_site

        refresh_site(Path(str(cfg.ledger.out_dir)))  # the site's index shows the ledger's findings
    return {
        "paths": paths,
        "statuses": dict(zip(frame["claim"], frame["status"], strict=True)),
        "counts": status_counts(frame),
    }


def ledger_line(summary: dict[str, Any]) -> str:
    """What the stage prints: where the ledger is and its status counts."""
    return f"ledger: {summary['counts']} -> {summary['paths']['md']}"
