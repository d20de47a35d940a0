"""The `model:` (and `dataset:`) config of a benchmark, composed as `python -m src.run` composes it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from src.errors import ConfigError
from src.models.instantiate import resolve_target

CONF_DIR = Path(__file__).resolve().parent.parent.parent / "conf"


def _compose(overrides: list[str], group: str, resolve: bool = True) -> dict[str, Any]:
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    return OmegaConf.to_container(cfg[group], resolve=resolve)  # type: ignore[return-value]


#: The key of conf/compare.yaml that names a benchmarked model's data.
BENCH_DATA_KEY = "compare.bench.data"


def load_model_config(
    name: str, profile: str, task: str | None = None, dataset: str | None = None
) -> dict[str, Any]:
    """The `model:` group as `python -m src.run [task=<task>] [dataset=<dataset>] model=<name>
    profile=<profile>` composes it (conf/model_profile/<name>_<profile>.yaml included; `task=nerf` also
    sets the NeRF dataset that `model.background` refers to; `dataset=volumetric` gives the KPCN family
    the sequences' one `radiance` branch and its `in_channels`, as the `unet_vs_kpcn` study trains it).
    Without `dataset`, a model whose class reads branches the default data lack (the U-Net KPCN: the
    sequences' `radiance`) is composed with the data conf/compare.yaml names for it (`bench.data`), so
    its `in_channels` are its data's; a model it does not name is a one-line ConfigError."""
    overrides = ([f"task={task}"] if task else []) + ([f"dataset={dataset}"] if dataset else [])
    overrides += [f"model={name}", f"profile={profile}"]
    model = _compose(overrides, "model")
    reads = set(getattr(resolve_target(model), "branches", ()))
    default = _compose(overrides, "dataset", resolve=False)
    if not reads or reads <= set(default.get("branches") or ()):
        return model
    lacking = f"model {name} reads branches {sorted(reads)}, which dataset={default.get('name')} lacks"
    if dataset is not None:
        raise ConfigError(f"dataset={dataset}: {lacking}; expected a dataset with those branches")
    named = _compose(overrides, "compare").get("bench", {}).get("data", {}).get(name)
    if named is None:
        raise ConfigError(
            f"{BENCH_DATA_KEY}.{name}: missing; {lacking}; expected conf/compare.yaml to name its data"
        )
    return _compose([*overrides, f"dataset={named}"], "model")


def load_dataset_config(task: str, profile: str) -> dict[str, Any]:
    """The `dataset:` group as `python -m src.run task=<task> profile=<profile>` composes it (the task's
    default dataset, with its task profile's overrides)."""
    return _compose([f"task={task}", f"profile={profile}"], "dataset")


def load_task_config(task: str, profile: str) -> dict[str, Any]:
    """The `task:` group as `python -m src.run task=<task> profile=<profile>` composes it, unresolved (its
    run paths need a Hydra run)."""
    return _compose([f"task={task}", f"profile={profile}"], "task", resolve=False)
