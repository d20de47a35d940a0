"""`Tracker`: what a stage logs into its MLflow run (metrics, artifacts, tags), by run id."""

from __future__ import annotations

import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from mlflow.entities import Metric, RunTag
from mlflow.tracking import MlflowClient
from mlflow.utils.validation import MAX_METRICS_PER_BATCH

from src.tracking.run_config import log_params, param_key


class Tracker:
    """Logs to one MLflow run by id; with `run_id=None` (tracking disabled) every method is a no-op.

    It goes through `MlflowClient` with an explicit run id, so logging never depends on which fluent
    run is active in the process.
    """

    def __init__(self, run_id: str | None = None):
        self.run_id = run_id
        self._client = MlflowClient() if run_id else None
        self._logged: set[tuple[str, int]] = set()  # (key, step) points not to log again (see below)

    @property
    def enabled(self) -> bool:
        return self.run_id is not None

    def skip_logged_after(self, step: int) -> None:
        """A training resumed from its checkpoint of `step` replays the steps after it, and a crash no
        handler saw (SIGKILL, OOM) left some of them logged in this run already: those (key, step) points
        are not logged again, so the run's history is the uninterrupted run's, one point per step (the
        replayed values are the same: training is deterministic given the checkpoint)."""
        if not self.enabled:
            return
        keys = self._client.get_run(self.run_id).data.metrics
        self._logged = {
            (m.key, m.step)
            for key in keys
            for m in self._client.get_metric_history(self.run_id, key)
            if m.step > step
        }

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        """Log several metrics at one step (and one timestamp)."""
        if not self.enabled or not metrics:
            return
        stamp = int(time.time() * 1000)
        entries = [Metric(param_key(k), float(v), stamp, step or 0) for k, v in metrics.items()]
        entries = [m for m in entries if (m.key, m.step) not in self._logged]
        for i in range(0, len(entries), MAX_METRICS_PER_BATCH):
            self._client.log_batch(self.run_id, metrics=entries[i : i + MAX_METRICS_PER_BATCH])

    def log_params(self, params: Mapping[str, Any]) -> None:
        """Log params (values as strings; names made MLflow-safe), in batches of MLflow's limit."""
        if self.enabled and params:
            log_params(self._client, self.run_id, {param_key(str(k)): str(v) for k, v in params.items()})

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
