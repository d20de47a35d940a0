"""A study's jobs, each with the digest of its configuration, and which of them are done.

A study is a sweep file (`conf/sweep/<name>.yaml`, `python -m src.run -m +sweep=<name>`). Its jobs are
the product of its `hydra.sweeper.params` (expanded by Hydra's own override parser, as the basic sweeper
expands them); each job's config is composed as the job will compose it, so its `config_digest` is the one
the job tags its run with (`nrbench.config_digest`): a job is done when the tracking store holds a
FINISHED run of that digest.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import statistics
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError, one_line
from src.provenance import config_digest
from src.report.claims import load_claims
from src.tracking.finished import FinishedRun

ROOT = Path(__file__).resolve().parents[2]
CONF = ROOT / "conf"
#: What the data stages read: jobs that agree on these share their rendered and prepared data.
DATA_KEYS = ("dataset", "data_seed", "render")
#: The stages that train or search: the data stages are a task's stages before the first of them.
WORK_STAGES = ("train", "search", "select_features")


@dataclass(frozen=True)
class StudyJob:
    study: str
    overrides: tuple[str, ...]  # this job's values of the swept keys, e.g. ("model=kpcn", "seed=0")
    digest: str  # `config_digest` of its config: what its run is tagged with
    data: str  # jobs with the same value share their data (`DATA_KEYS`, the task and its preprocessing)
    data_stages: tuple[str, ...]
    model: str
    uri: str
    experiment: str


def ledger_studies(claims_file: str | Path, profile: str) -> list[str]:
    """The studies the ledger's claims name as a source of runs, for the claims meaningful at `profile`,
    in the order of the claims file."""
    studies: list[str] = []
    for claim in load_claims(claims_file):
        if profile not in claim.profiles:
            continue
        for kind, name in claim.sources:
            if kind == "study" and name not in studies:
                studies.append(name)
    return studies


def expand(params: dict[str, str]) -> list[tuple[str, ...]]:
    """Every job of sweeper params {key: "a,b,c" | "range(3)" | value}: the product in key order, as
    Hydra's basic sweeper makes it, each job a tuple of `key=value` overrides."""
    parsed = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in params.items()])
    axes = []
    for override in parsed:
        values = (
            list(override.sweep_string_iterator())
            if override.is_sweep_override()
            else [override.get_value_element_as_str()]
        )
        axes.append([f"{override.get_key_element()}={v}" for v in values])
    return list(itertools.product(*axes))


def _compose(overrides: Sequence[str], hydra_config: bool = False) -> DictConfig:
    """The root config of `overrides` as a job composes it (paths at the repository root and a stand-in
    run folder, neither part of a digest); a bad override is one line."""
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        try:
            return compose(
                config_name="config",
                overrides=[*overrides, f"paths.root={ROOT}", "paths.run_dir=/nrbench-plan"],
                return_hydra_config=hydra_config,
            )
        except Exception as err:  # Hydra raises several types for a bad override or a missing group
            raise ConfigError(f"{' '.join(overrides)}: {one_line(err)}") from None


def sweep_params(study: str, profile: str, overrides: Sequence[str] = ()) -> dict[str, str]:
    """The study's `hydra.sweeper.params` at `profile`, interpolations resolved."""
    cfg = _compose([f"+sweep={study}", f"profile={profile}", *overrides], hydra_config=True)
    params = OmegaConf.to_container(cfg.hydra.sweeper.params, resolve=True) or {}
    return {str(k): str(v) for k, v in params.items()}


def data_identity(cfg: DictConfig) -> str:
    """A short hash of what the data stages read (`DATA_KEYS`, the task's name and preprocessing): jobs
    with the same one share their rendered and prepared data."""

    def resolved(key: str) -> Any:
        node = OmegaConf.select(cfg, key)
        return OmegaConf.to_container(node, resolve=True) if OmegaConf.is_config(node) else node

    what = {key: resolved(key) for key in (*DATA_KEYS, "task.name", "task.preprocess")}
    return hashlib.sha256(json.dumps(what, sort_keys=True, default=str).encode()).hexdigest()[:12]


def _data_stages(cfg: DictConfig) -> tuple[str, ...]:
    stages = [str(s) for s in cfg.task.stages]
    first_work = next((i for i, s in enumerate(stages) if s in WORK_STAGES), len(stages))
    return tuple(stages[:first_work])


def study_jobs(study: str, profile: str, overrides: Sequence[str] = ()) -> list[StudyJob]:
    """Every job of study `study` at `profile`, with `overrides` (the user's, e.g. a launcher's, given to
    every job as the launch gives them)."""
    jobs = []
    for values in expand(sweep_params(study, profile, overrides)):
        cfg = _compose([f"+sweep={study}", f"profile={profile}", *overrides, *values])
        jobs.append(
            StudyJob(
                study=study,
                overrides=values,
                digest=config_digest(cfg),
                data=data_identity(cfg),
                data_stages=_data_stages(cfg),
                model=str(cfg.model.name),
                uri=str(cfg.tracking.uri),
                experiment=str(cfg.tracking.experiment),
            )
        )
    return jobs


def estimate_seconds(job: StudyJob, done: dict[str, FinishedRun], jobs: Sequence[StudyJob]) -> float | None:
    """A job's expected duration: the median of its study's done jobs of the same model, else of all its
    study's done jobs; None when none is done yet."""
    finished = [done[j.digest] for j in jobs if j.digest in done]
    same_model = [run.seconds for run in finished if run.model == job.model]
    pool = same_model or [run.seconds for run in finished]
    return statistics.median(pool) if pool else None
