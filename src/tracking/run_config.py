"""A run's config as MLflow holds it: the flattened resolved config as params (names and values within
MLflow's limits, logged in batches) and the resolved config as `config.yaml` text."""

from __future__ import annotations

import json
import re
from collections.abc import Mapping
from typing import Any

from mlflow.entities import Param
from mlflow.tracking import MlflowClient
from mlflow.utils.validation import MAX_PARAM_VAL_LENGTH, MAX_PARAMS_TAGS_PER_BATCH
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

TRUNCATED = "...[truncated]"


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


def param_key(key: str) -> str:
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
            flat[param_key(prefix)] = _param_value(value)

    walk("", resolved_container(cfg))
    return flat


def config_yaml(cfg) -> str:
    """The resolved config as YAML (the run's `config.yaml` artifact)."""
    try:
        return OmegaConf.to_yaml(cfg, resolve=True)
    except OmegaConfBaseException:
        return OmegaConf.to_yaml(OmegaConf.create(_plain(cfg)))


def log_params(client: MlflowClient, run_id: str, params: Mapping[str, str]) -> None:
    """Log params in batches of MLflow's per-request limit (100)."""
    entries = [Param(k, v) for k, v in params.items()]
    for i in range(0, len(entries), MAX_PARAMS_TAGS_PER_BATCH):
        client.log_batch(run_id, params=entries[i : i + MAX_PARAMS_TAGS_PER_BATCH])
