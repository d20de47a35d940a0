"""MLflow run lifecycle: one run per Hydra job, children of a sweep's parent run in a multirun.

The parent run of a multirun is created by `src.tracking.callbacks.MlflowSweepCallback` before any job
starts; it writes `<sweep dir>/mlflow_parent.json`, which every job of the sweep reads here to attach
itself as a child (`mlflow.parentRunId`). Jobs may run in other processes or on other machines
(launcher plugins), so the file, not process state, is the link between them.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import mlflow
from mlflow.entities import RunStatus, RunTag
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from src.errors import ConfigError
from src.launch.requeue import requeue_pending
from src.multirun import PARENT_FILE, read_parent
from src.provenance import git_commit
from src.tracking.experiment import first_line, run_url_line, setup_tracking
from src.tracking.run_config import config_yaml, flatten_config, log_params
from src.tracking.tracker import Tracker

log = logging.getLogger("nrbench.tracking")


def _hydra_job() -> tuple[str, Path | None]:
    """This job's task overrides (space-joined) and, in a multirun, the absolute sweep dir."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if not HydraConfig.initialized():
        return "", None
    hydra_cfg = HydraConfig.get()
    overrides = " ".join(str(o) for o in hydra_cfg.overrides.task)
    if hydra_cfg.mode != RunMode.MULTIRUN:
        return overrides, None
    # Relative to the launch directory, not the cwd (hydra.job.chdir=true moves the cwd).
    return overrides, Path(hydra_cfg.runtime.cwd) / str(hydra_cfg.sweep.dir)


def _parent_run_id(sweep_dir: Path, uri: str) -> str | None:
    """Parent run id for a job of the sweep in `sweep_dir`; None (with a warning) if unusable."""
    record = read_parent(sweep_dir)
    if record is None:
        log.warning(
            "multirun without %s in %s (is the mlflow_sweep callback configured?): "
            "this job's MLflow run is top-level",
            PARENT_FILE,
            sweep_dir,
        )
        return None
    if record.get("tracking_uri") != uri:
        log.warning(
            "sweep parent run lives in %s, this job logs to %s: this job's MLflow run is top-level",
            record.get("tracking_uri"),
            uri,
        )
        return None
    return record["run_id"]


def _base_tags(tags: Mapping[str, Any], overrides: str, sweep_dir: Path | None) -> dict[str, str]:
    """Caller tags plus provenance: git commit (without `+dirty`), dirty flag, overrides, sweep dir."""
    commit = git_commit()
    out = {str(k): str(v) for k, v in tags.items()}
    out["nrbench.git_commit"] = commit.removesuffix("+dirty")
    out["nrbench.git_dirty"] = str(commit.endswith("+dirty")).lower()
    out["nrbench.hydra_job"] = overrides
    if sweep_dir is not None:
        out["nrbench.sweep_dir"] = str(sweep_dir)
    return out


def _log_new_params(client: MlflowClient, run_id: str, params: Mapping[str, str]) -> None:
    """On resume: MLflow refuses to change a logged param, so log only keys it does not have yet."""
    existing = client.get_run(run_id).data.params
    changed = sorted(k for k, v in params.items() if k in existing and existing[k] != v)
    if changed:
        log.warning(
            "resumed run %s keeps its original params; changed now: %s",
            run_id,
            ", ".join(changed[:10]) + (" ..." if len(changed) > 10 else ""),
        )
    log_params(client, run_id, {k: v for k, v in params.items() if k not in existing})


def _start(cfg, experiment_id: str, run_name: str, tags: dict[str, str], parent_id: str | None):
    """Start the fluent run (so library code calling `mlflow.log_*` inside the job lands in it too),
    then log its params and the resolved config. Inside another active run it becomes a child of it."""
    client = MlflowClient()
    run = mlflow.start_run(
        experiment_id=experiment_id,
        run_name=run_name,
        nested=parent_id is not None or mlflow.active_run() is not None,
        parent_run_id=parent_id,
        tags=tags,
    )
    log_params(client, run.info.run_id, flatten_config(cfg))
    client.log_text(run.info.run_id, config_yaml(cfg), "config.yaml")
    return run


def _resume(cfg, run_id: str, tags: dict[str, str]):
    """Reopen run `run_id`: refresh tags, add params it lacks, keep its original `config.yaml`."""
    client = MlflowClient()
    try:
        run = mlflow.start_run(run_id=run_id, nested=mlflow.active_run() is not None)
    except MlflowException as err:
        raise ConfigError(f"resume run {run_id}: cannot reopen it ({first_line(err)})") from None
    client.log_batch(run_id, tags=[RunTag(k, v) for k, v in tags.items()])
    _log_new_params(client, run_id, flatten_config(cfg))
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    client.log_text(run_id, config_yaml(cfg), f"resumed/config-{stamp}.yaml")
    return run


def _resumable(run_id: str) -> bool:
    """Whether run `run_id` exists, not deleted, in the current tracking store."""
    try:
        return MlflowClient().get_run(run_id).info.lifecycle_stage != "deleted"
    except MlflowException:
        return False


def _end(run_id: str, status: str, parent_id: str | None) -> None:
    """End the fluent run; a failed or killed child also marks its sweep's parent run.

    Hydra's sweepers re-raise a failed job's exception, so `on_multirun_end` (which would set the
    parent's final status) never runs then; without this the parent would stay RUNNING forever.
    """
    active = mlflow.active_run()
    if active is not None and active.info.run_id == run_id:
        mlflow.end_run(status=status)
    else:
        MlflowClient().set_terminated(run_id, status)
    if parent_id is not None and status != RunStatus.to_string(RunStatus.FINISHED):
        MlflowClient().set_terminated(parent_id, status)


@contextlib.contextmanager
def job_run(
    cfg, *, run_name: str, tags: Mapping[str, str], resume_run_id: str | None = None
) -> Iterator[Tracker]:
    """One MLflow run around a Hydra job; yields a `Tracker` (a no-op one if tracking is disabled).

    New runs get params (the flattened resolved config), provenance tags and a `config.yaml`
    artifact; in a Hydra multirun they become children of the sweep's parent run. `resume_run_id`
    reopens an existing run (after an interrupted training) and appends to it. The run ends
    FINISHED, FAILED on an exception (re-raised), KILLED on Ctrl-C or when the job exits to be requeued
    (then its sweep's parent run is left running).
    """
    if not cfg.tracking.enabled:
        yield Tracker(None)
        return
    overrides, sweep_dir = _hydra_job()
    experiment_id = setup_tracking(cfg.tracking)
    all_tags = _base_tags(tags, overrides, sweep_dir)
    parent_id = None
    if resume_run_id and not _resumable(resume_run_id):
        # E.g. a checkpoint copied from another machine: train on, into a new run, rather than stop.
        log.warning(
            "MLflow run %s (to resume) is not in %s or is deleted: starting a new run",
            resume_run_id,
            mlflow.get_tracking_uri(),
        )
        resume_run_id = None
    if resume_run_id:
        run = _resume(cfg, resume_run_id, all_tags)
    else:
        if sweep_dir is not None:
            parent_id = _parent_run_id(sweep_dir, mlflow.get_tracking_uri())
        run = _start(cfg, experiment_id, run_name, all_tags, parent_id)
    run_id = run.info.run_id
    # At the start, so a long training can be watched; printed, not logged: a job's log level may hide it.
    # The run's own experiment: a resumed run may live in another than tracking.experiment.
    print(run_url_line(mlflow.get_tracking_uri(), run.info.experiment_id, run_id), flush=True)
    try:
        yield Tracker(run_id)
    except KeyboardInterrupt:
        _end(run_id, "KILLED", parent_id)
        raise
    except SystemExit as exc:
        if requeue_pending():  # submitit's exit after requeueing: the restarted job reopens this run
            _end(run_id, "KILLED", None)
        else:  # sys.exit(0) inside a job is a clean end, any other code a failure
            _end(run_id, "FINISHED" if exc.code in (0, None) else "FAILED", parent_id)
        raise
    except BaseException:
        _end(run_id, "FAILED", parent_id)
        raise
    _end(run_id, "FINISHED", parent_id)


@contextlib.contextmanager
def standalone_run(tracking_cfg, *, run_name: str, tags: Mapping[str, str]) -> Iterator[Tracker]:
    """One MLflow run outside a Hydra job (`python -m src.bench ... --log`), in experiment
    `tracking_cfg.experiment` of store `tracking_cfg.uri` (see `setup_tracking`), with the provenance tags
    of a job's run (git commit and dirty flag); it ends FINISHED, or FAILED on an exception (re-raised)."""
    experiment_id = setup_tracking(tracking_cfg)
    all_tags = _base_tags(tags, "", None)
    del all_tags["nrbench.hydra_job"]  # no Hydra job
    run = MlflowClient().create_run(experiment_id, run_name=run_name, tags=all_tags)
    run_id = run.info.run_id
    print(run_url_line(mlflow.get_tracking_uri(), experiment_id, run_id), flush=True)
    try:
        yield Tracker(run_id)
    except BaseException:
        MlflowClient().set_terminated(run_id, "FAILED")
        raise
    MlflowClient().set_terminated(run_id, "FINISHED")
