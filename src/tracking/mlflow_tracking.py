"""MLflow run lifecycle: one run per Hydra job, children of a sweep's parent run in a multirun.

The parent run of a multirun is created by `src.tracking.callbacks.MlflowSweepCallback` before any job
starts; it writes `<sweep dir>/mlflow_parent.json`, which every job of the sweep reads here to attach
itself as a child (`mlflow.parentRunId`). Jobs may run in other processes or on other machines
(launcher plugins), so the file, not process state, is the link between them.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import re
import time
from collections.abc import Iterator, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import mlflow
import pandas as pd
from mlflow.entities import Metric, Param, RunStatus, RunTag
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient
from mlflow.utils.mlflow_tags import MLFLOW_PARENT_RUN_ID
from mlflow.utils.validation import MAX_METRICS_PER_BATCH, MAX_PARAM_VAL_LENGTH, MAX_PARAMS_TAGS_PER_BATCH
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from src.errors import ConfigError
from src.multirun import PARENT_FILE, quiet_mlflow_logs, read_parent
from src.provenance import git_commit

log = logging.getLogger("nrbench.tracking")

TRUNCATED = "...[truncated]"
# Schemes whose artifact location the server decides (a local file URI would be unreadable by it).
_REMOTE_SCHEMES = ("http://", "https://", "databricks")

# Default comparison columns: display name -> column of `mlflow.search_runs`' frame.
DEFAULT_COLUMNS: dict[str, str] = {
    "model": "tags.nrbench.model",
    "params": "metrics.param_count",
    "PSNR": "metrics.eval_psnr",
    "SSIM": "metrics.eval_ssim",
    "relMSE": "metrics.eval_relmse",
    "noisy relMSE": "metrics.eval_noisy_relmse",
    "train time s": "metrics.train_time_s",
    "inference ms/MP": "metrics.eval_ms_per_mpixel",
    "status": "status",
}
_SORT_COLUMN = "relMSE"
# Per-column display formats for `format_table`; other float columns use `{:.4g}`.
_FORMATS: dict[str, str] = {
    "params": "{:,.0f}",
    "PSNR": "{:.2f}",
    "SSIM": "{:.4f}",
    "relMSE": "{:.4g}",
    "noisy relMSE": "{:.4g}",
    "train time s": "{:.1f}",
    "inference ms/MP": "{:.1f}",
}


def _one_line(err: BaseException) -> str:
    """The first line of an exception message (MLflow's often carry a traceback-like tail)."""
    text = str(err).strip().splitlines()
    return text[0] if text else type(err).__name__


def setup_tracking(tracking_cfg) -> str:
    """Point MLflow at `tracking_cfg.uri` and return the id of experiment `tracking_cfg.experiment`.

    The experiment is created if missing, with its artifacts under `tracking_cfg.artifact_root` (local
    stores only: with a tracking server the server's artifact root applies). Two processes may create
    it at the same moment; the loser's create fails and it reads the winner's experiment instead.
    """
    uri, name = str(tracking_cfg.uri), str(tracking_cfg.experiment)
    quiet_mlflow_logs()
    mlflow.set_tracking_uri(uri)
    try:
        client = MlflowClient(tracking_uri=uri)
        experiment = client.get_experiment_by_name(name)
        if experiment is None:
            return _create_experiment(client, name, _artifact_location(tracking_cfg, uri))
    except MlflowException as err:
        raise ConfigError(f"tracking.uri={uri!r}: cannot use this MLflow store ({_one_line(err)})") from None
    except Exception as err:  # SQLAlchemy / OS errors for a bad path surface as plain exceptions
        raise ConfigError(f"tracking.uri={uri!r}: cannot open this MLflow store ({_one_line(err)})") from None
    if experiment.lifecycle_stage == "deleted":
        raise ConfigError(
            f"tracking.experiment={name!r} is deleted in {uri}: restore it "
            f"(`mlflow experiments restore --experiment-id {experiment.experiment_id}`) or pick another name"
        )
    return experiment.experiment_id


def _artifact_location(tracking_cfg, uri: str) -> str | None:
    """`file://` URI of `tracking.artifact_root` for a local store, else None (server's default)."""
    if hasattr(tracking_cfg, "get"):  # DictConfig or dict
        root = tracking_cfg.get("artifact_root")
    else:
        root = getattr(tracking_cfg, "artifact_root", None)
    if not root or uri.startswith(_REMOTE_SCHEMES):
        return None
    return Path(str(root)).expanduser().resolve().as_uri()


def _create_experiment(client: MlflowClient, name: str, artifact_location: str | None) -> str:
    """Create the experiment; if another process won the race, return the one it created."""
    try:
        return client.create_experiment(name, artifact_location=artifact_location)
    except Exception:  # "already exists", or SQLite's "database is locked" while the winner writes
        experiment = client.get_experiment_by_name(name)
        if experiment is None:
            raise
        return experiment.experiment_id


# ----------------------------------------------------------------------------------------- config


def _plain(node: DictConfig | ListConfig) -> Any:
    """Resolved container; a value that cannot be resolved here (e.g. `${hydra:...}` outside a Hydra
    job, or `???`) is kept as its raw text instead of failing the whole run."""
    keys = node.keys() if isinstance(node, DictConfig) else range(len(node))
    out = {}
    for key in keys:
        try:
            value = node[key]
        except OmegaConfBaseException:
            value = str(node._get_node(key)._value())
        out[key] = _plain(value) if isinstance(value, DictConfig | ListConfig) else value
    return out if isinstance(node, DictConfig) else list(out.values())


def resolved_container(cfg) -> Any:
    """`cfg` as plain dicts/lists with interpolations resolved where possible."""
    if isinstance(cfg, DictConfig | ListConfig):
        try:
            return OmegaConf.to_container(cfg, resolve=True)
        except OmegaConfBaseException:
            return _plain(cfg)
    return cfg


def _param_value(value: Any) -> str:
    """A param value as MLflow stores it: a string within MLflow's length limit (lists as JSON)."""
    text = json.dumps(value, default=str) if isinstance(value, list | tuple) else str(value)
    if len(text) > MAX_PARAM_VAL_LENGTH:
        text = text[: MAX_PARAM_VAL_LENGTH - len(TRUNCATED)] + TRUNCATED
    return text


def _param_key(key: str) -> str:
    """MLflow accepts only alphanumerics, `_ - . /` and spaces in names; replace anything else."""
    return re.sub(r"[^/\w.\- ]", "_", key)


def flatten_config(cfg, sep: str = ".") -> dict[str, str]:
    """Flatten a (resolved) config into `{"a.b.c": "value"}` strings, lists as their JSON text.

    Every value fits MLflow's param value limit (6000 characters); longer ones are cut and end with
    `...[truncated]`. An empty dict becomes the param `"{}"` so its key still shows up.
    """
    flat: dict[str, str] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, Mapping) and value:
            for key, sub in value.items():
                walk(f"{prefix}{sep}{key}" if prefix else str(key), sub)
        else:
            flat[_param_key(prefix)] = _param_value(value)

    walk("", resolved_container(cfg))
    return flat


def config_yaml(cfg) -> str:
    """The resolved config as YAML (the run's `config.yaml` artifact)."""
    try:
        return OmegaConf.to_yaml(cfg, resolve=True)
    except OmegaConfBaseException:
        return OmegaConf.to_yaml(OmegaConf.create(_plain(cfg)))


# ---------------------------------------------------------------------------------------- tracker


class Tracker:
    """Logs to one MLflow run by id; with `run_id=None` (tracking disabled) every method is a no-op.

    It goes through `MlflowClient` with an explicit run id, so logging never depends on which fluent
    run is active in the process.
    """

    def __init__(self, run_id: str | None = None):
        self.run_id = run_id
        self._client = MlflowClient() if run_id else None

    @property
    def enabled(self) -> bool:
        return self.run_id is not None

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        """Log several metrics at one step (and one timestamp)."""
        if not self.enabled or not metrics:
            return
        stamp = int(time.time() * 1000)
        entries = [Metric(_param_key(k), float(v), stamp, step or 0) for k, v in metrics.items()]
        for i in range(0, len(entries), MAX_METRICS_PER_BATCH):
            self._client.log_batch(self.run_id, metrics=entries[i : i + MAX_METRICS_PER_BATCH])

    def log_metric(self, key: str, value: float, step: int | None = None) -> None:
        self.log_metrics({key: value}, step=step)

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        if self.enabled:
            self._client.log_artifact(self.run_id, str(path), artifact_path)

    def log_artifacts(self, directory: str | Path, artifact_path: str | None = None) -> None:
        if self.enabled:
            self._client.log_artifacts(self.run_id, str(directory), artifact_path)

    def log_dict(self, obj: Any, artifact_file: str) -> None:
        """Log a dict/list as a JSON (or YAML, by extension) artifact."""
        if self.enabled:
            self._client.log_dict(self.run_id, obj, artifact_file)

    def log_text(self, text: str, artifact_file: str) -> None:
        if self.enabled:
            self._client.log_text(self.run_id, text, artifact_file)

    def set_tags(self, tags: Mapping[str, Any]) -> None:
        if self.enabled and tags:
            self._client.log_batch(self.run_id, tags=[RunTag(k, str(v)) for k, v in tags.items()])


# --------------------------------------------------------------------------------------- job runs


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


def log_params(client: MlflowClient, run_id: str, params: Mapping[str, str]) -> None:
    """Log params in batches of MLflow's per-request limit (100)."""
    entries = [Param(k, v) for k, v in params.items()]
    for i in range(0, len(entries), MAX_PARAMS_TAGS_PER_BATCH):
        client.log_batch(run_id, params=entries[i : i + MAX_PARAMS_TAGS_PER_BATCH])


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
        raise ConfigError(f"resume run {run_id}: cannot reopen it ({_one_line(err)})") from None
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
    FINISHED, FAILED on an exception (re-raised) or KILLED on Ctrl-C.
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
        run_id = _resume(cfg, resume_run_id, all_tags).info.run_id
    else:
        if sweep_dir is not None:
            parent_id = _parent_run_id(sweep_dir, mlflow.get_tracking_uri())
        run_id = _start(cfg, experiment_id, run_name, all_tags, parent_id).info.run_id
    try:
        yield Tracker(run_id)
    except KeyboardInterrupt:
        _end(run_id, "KILLED", parent_id)
        raise
    except SystemExit as exc:  # sys.exit(0) inside a job is a clean end, any other code a failure
        _end(run_id, "FINISHED" if exc.code in (0, None) else "FAILED", parent_id)
        raise
    except BaseException:
        _end(run_id, "FAILED", parent_id)
        raise
    _end(run_id, "FINISHED", parent_id)


# ------------------------------------------------------------------------------------ comparisons


def comparison_table(
    parent_run_id: str | None = None,
    experiment: str | None = None,
    columns: Mapping[str, str] | None = None,
) -> pd.DataFrame:
    """One row per run: the children of `parent_run_id`, or else every job run of `experiment`.

    `columns` maps display names to `mlflow.search_runs` columns (`metrics.x`, `params.x`, `tags.x`,
    `status`, ...); one a run lacks shows NaN. Rows are sorted by relMSE, best first, when shown.
    """
    columns = dict(DEFAULT_COLUMNS if columns is None else columns)
    runs = _search(parent_run_id, experiment)
    missing = pd.Series(math.nan, index=runs.index)
    table = pd.DataFrame({name: runs.get(col, missing) for name, col in columns.items()})
    if _SORT_COLUMN in table:
        table = table.sort_values(_SORT_COLUMN, na_position="last", kind="stable")
    return table.reset_index(drop=True)


def _search(parent_run_id: str | None, experiment: str | None) -> pd.DataFrame:
    """`mlflow.search_runs` frame for the chosen runs (sweep parents excluded)."""
    if parent_run_id is None and experiment is None:
        raise ValueError("comparison_table needs a parent_run_id or an experiment")
    where = f"tags.{MLFLOW_PARENT_RUN_ID} = '{parent_run_id}'" if parent_run_id else ""
    scope = {"experiment_names": [experiment]} if experiment else {"search_all_experiments": True}
    runs = mlflow.search_runs(filter_string=where, output_format="pandas", **scope)
    if "tags.nrbench.sweep_parent" in runs:
        runs = runs[runs["tags.nrbench.sweep_parent"] != "true"]
    # Oldest first, so equal relMSE (or none) keeps the sweep's job order.
    return runs.sort_values("start_time", kind="stable") if "start_time" in runs else runs


def _formatter(column: str, values: pd.Series):
    """Formatter for one column: its `_FORMATS` entry, `{:.4g}` for other floats, `-` for missing."""
    fmt = _FORMATS.get(column)
    if fmt is None and pd.api.types.is_float_dtype(values):
        fmt = "{:.4g}"

    def render(value: Any) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "-"
        if fmt is not None and isinstance(value, int | float):
            return fmt.format(value)
        return str(value)

    return render


def format_table(df: pd.DataFrame) -> str:
    """Plain-text table (no `tabulate` needed) with per-column number formats and `-` for missing."""
    if df.empty:
        return "(no runs)"
    formatters = {col: _formatter(col, df[col]) for col in df.columns}
    return df.to_string(index=False, formatters=formatters, na_rep="-")
