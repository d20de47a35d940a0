"""The MLflow store and experiment a run logs to: pointing MLflow at `tracking.uri`, creating the
experiment (race-safe) with its artifact location, and one-line errors for a store that cannot be used."""

from __future__ import annotations

from pathlib import Path

import mlflow
from mlflow.exceptions import MlflowException
from mlflow.tracking import MlflowClient

from src.errors import ConfigError
from src.multirun import quiet_mlflow_logs

# Schemes whose artifact location the server decides (a local file URI would be unreadable by it).
_REMOTE_SCHEMES = ("http://", "https://", "databricks")


#: Where `bash scripts/mlflow_ui.sh` serves a local store (its default port) and the store it serves unless
#: MLFLOW_TRACKING_URI names another: the project's `mlflow.db`.
UI_SCRIPT_URL = "http://127.0.0.1:5000"
PROJECT_STORE = f"sqlite:///{Path(__file__).resolve().parents[2] / 'mlflow.db'}"


def run_url_line(uri: str, experiment_id: str, run_id: str) -> str:
    """The line a job prints about its run: the URL of the run's page in MLflow's UI (which opens the run
    whatever the UI's GenAI | Model training switch says, unlike the experiment's page).

    A tracking server (`http(s)://`) is its own UI. A local store (SQLite, another database) has no UI
    until `scripts/mlflow_ui.sh` serves it, at port 5000 unless told otherwise: the line says so, with
    the store when it is not the one the script serves by default. Databricks: no URL is known here."""
    page = f"#/experiments/{experiment_id}/runs/{run_id}"
    if uri.startswith(("http://", "https://")):
        return f"MLflow run: {uri.rstrip('/')}/{page}"
    if uri.startswith("databricks"):
        return f"MLflow run {run_id} (experiment {experiment_id}) in {uri}"
    script = "bash scripts/mlflow_ui.sh"
    if uri != PROJECT_STORE:
        script = f"MLFLOW_TRACKING_URI={uri} {script}"
    return f"MLflow run: {UI_SCRIPT_URL}/{page} (once the UI runs: {script})"


def first_line(err: BaseException) -> str:
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
        raise ConfigError(f"tracking.uri={uri!r}: cannot use this MLflow store ({first_line(err)})") from None
    except Exception as err:  # SQLAlchemy / OS errors for a bad path surface as plain exceptions
        raise ConfigError(
            f"tracking.uri={uri!r}: cannot open this MLflow store ({first_line(err)})"
        ) from None
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
