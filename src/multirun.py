"""What the Hydra callbacks of a multirun share: its absolute sweep dir, the resolved sections of the
launcher's config, and the record of the sweep's MLflow parent run that the tracking callback leaves in
the sweep dir (the report callback reads it). A module of its own so that `src.tracking` (which writes
runs) and `src.report` (which reads them) need not import each other."""

from __future__ import annotations

import copy
import json
import logging
import os
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from src.errors import ConfigError

#: The sweep's parent-run record, in the sweep dir: {"run_id", "experiment_id", "tracking_uri", "run_name"}.
PARENT_FILE = "mlflow_parent.json"


def sweep_dir(config: DictConfig) -> Path:
    """Absolute sweep dir; a relative `hydra.sweep.dir` is relative to the launch directory."""
    return Path(config.hydra.runtime.cwd or os.getcwd()) / str(config.hydra.sweep.dir)


def read_parent(directory: Path) -> dict | None:
    """The sweep's parent-run record (`mlflow_parent.json`), or None if the tracking callback did not run."""
    try:
        return json.loads((Path(directory) / PARENT_FILE).read_text())
    except FileNotFoundError:
        return None


def resolved_section(config: DictConfig, key: str) -> DictConfig:
    """The resolved section `key` (tracking, report) of the launcher's config.

    Before any job starts Hydra has not set `HydraConfig`, so `${hydra:runtime.cwd}` (behind
    `paths.root`, hence the default `tracking.uri`) cannot resolve. Set it from a copy of this config
    (whose `hydra.runtime.cwd` is already the launch dir) just for the resolution, then put it back.
    """
    holder = HydraConfig.instance()
    previous = holder.cfg
    scratch = copy.deepcopy(config)
    try:
        if previous is None:
            holder.set_config(scratch)
        return OmegaConf.create(OmegaConf.to_container(scratch[key], resolve=True))
    except OmegaConfBaseException as err:
        raise ConfigError(f"{key}: cannot resolve it in the sweep's launcher ({err.msg})") from None
    finally:
        holder.cfg = previous


def quiet_mlflow_logs() -> None:
    """Silence the database-migration chatter MLflow prints when it opens or creates a SQLite store,
    and its per-artifact download progress bars (one per run and file when a report reads curves)."""
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    for name in ("alembic", "mlflow.store.db.utils", "mlflow.store.tracking.sqlalchemy_store"):
        logging.getLogger(name).setLevel(logging.WARNING)
