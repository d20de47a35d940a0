"""Hydra callback: a parent MLflow run per multirun, and its comparison table when the sweep ends (the
report over the sweep is `src.report.sweep_callback`).

Configured in `conf/config.yaml` under `hydra.callbacks.mlflow_sweep`. The parent run is created with
`MlflowClient.create_run` (not `mlflow.start_run`), so no run is active in the launching process: with
Hydra's basic launcher the jobs run in this same process and start their own fluent runs.
"""

from __future__ import annotations

import logging
from datetime import datetime
from typing import TYPE_CHECKING, Any

from hydra.core.utils import JobReturn, JobStatus
from hydra.experimental.callback import Callback
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from src.io.atomic import atomic_write_json
from src.multirun import PARENT_FILE, read_parent, resolved_section, sweep_dir
from src.provenance import git_commit

if TYPE_CHECKING:
    import pandas as pd

# mlflow, pandas and src.tracking.comparison are imported where a multirun uses them: Hydra builds this
# callback in every `python -m src.run`, and importing them costs ~2.5 s a process (each DVC stage is one).

log = logging.getLogger("nrbench.tracking")

# The sweep table adds each job's overrides in front, so rows of a sweep over anything are told apart.
SWEEP_JOB_COLUMN = {"job": "tags.nrbench.hydra_job"}
_BAD_CHILD_STATUSES = ("FAILED", "KILLED")


def varying_overrides(jobs: pd.Series) -> pd.Series:
    """Each job's overrides less those every job shares (the sweep's own command line), so the column
    shows what tells the rows apart."""
    parts = jobs.fillna("").astype(str).str.split()
    if len(parts) < 2:
        return jobs
    common = set.intersection(*(set(p) for p in parts))
    return parts.map(lambda p: " ".join(o for o in p if o not in common))


class MlflowSweepCallback(Callback):
    """Creates the sweep's parent run before the jobs and closes it (with a table) after them."""

    def __init__(self) -> None:
        # The parent-run record of the sweep this launcher started (None: tracking off / not started).
        # Kept in memory: a record file left in a reused sweep dir by an earlier sweep must not be closed.
        self._record: dict | None = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        """Create the experiment and a RUNNING parent run; record it in `<sweep dir>/mlflow_parent.json`.

        Creating the experiment here, before any job, avoids parallel jobs racing to create it in
        SQLite. A stale record from an earlier sweep in the same dir is replaced.
        """
        tracking = resolved_section(config, "tracking")
        directory = sweep_dir(config)
        if not tracking.enabled:
            # A record left by an earlier sweep in a reused dir would attach jobs to a stale parent.
            (directory / PARENT_FILE).unlink(missing_ok=True)
            return
        from mlflow.tracking import MlflowClient

        from src.tracking.experiment import setup_tracking

        experiment_id = setup_tracking(tracking)
        overrides = " ".join(str(o) for o in config.hydra.overrides.task)
        commit = git_commit()
        task = OmegaConf.select(config, "task.name", default=None, throw_on_resolution_failure=False)
        run_name = f"sweep-{task or 'nrbench'}-{datetime.now():%Y%m%d-%H%M%S}"
        tags = {
            "nrbench.sweep_parent": "true",
            "nrbench.sweep_dir": str(directory),
            "nrbench.sweep_overrides": overrides,
            "nrbench.git_commit": commit.removesuffix("+dirty"),
            "nrbench.git_dirty": str(commit.endswith("+dirty")).lower(),
        }
        run = MlflowClient().create_run(experiment_id, tags=tags, run_name=run_name)
        record = {
            "run_id": run.info.run_id,
            "experiment_id": experiment_id,
            "tracking_uri": str(tracking.uri),
            "run_name": run_name,
        }
        atomic_write_json(directory / PARENT_FILE, record)
        self._record = record
        log.info("MLflow parent run %s (%s) for sweep %s", run_name, run.info.run_id, directory)

    def on_job_end(self, config: DictConfig, job_return: JobReturn, **kwargs: Any) -> None:
        """A job that failed outside its MLflow run (e.g. in config) still marks the parent FAILED."""
        if job_return.status != JobStatus.FAILED or config.hydra.mode != RunMode.MULTIRUN:
            return
        record = read_parent(sweep_dir(config))
        if record is not None:
            from mlflow.tracking import MlflowClient

            MlflowClient(tracking_uri=record["tracking_uri"]).set_terminated(record["run_id"], "FAILED")

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """Close the parent (FAILED if any child failed), print the comparison table and log it."""
        record = self._record
        if record is None:
            return

        import mlflow
        from mlflow.tracking import MlflowClient

        from src.tracking.comparison import DEFAULT_COLUMNS, comparison_table, format_table

        mlflow.set_tracking_uri(record["tracking_uri"])
        client = MlflowClient(tracking_uri=record["tracking_uri"])
        parent_id = record["run_id"]
        table = comparison_table(parent_id, columns=SWEEP_JOB_COLUMN | DEFAULT_COLUMNS)
        if not table.empty:
            table["job"] = varying_overrides(table["job"])
        failed = table["status"].isin(_BAD_CHILD_STATUSES).any() if not table.empty else False
        text = format_table(table)
        name = record.get("run_name", parent_id)
        header = f"== MLflow sweep {name}: {len(table)} runs (parent run {parent_id}) =="
        print(f"\n{header}\n{text}\n", flush=True)
        client.log_text(parent_id, table.to_csv(index=False), "comparison.csv")
        client.log_text(parent_id, text + "\n", "comparison.txt")
        client.set_terminated(parent_id, "FAILED" if failed else "FINISHED")
