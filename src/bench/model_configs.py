"""The `model:` (and `dataset:`) config of a benchmark, composed as `python -m src.run` composes it."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from src.models.instantiate import resolve_target

CONF_DIR = Path(__file__).resolve().parent.parent.parent / "conf"


def _compose(overrides: list[str], group: str, resolve: bool = True) -> dict[str, Any]:
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
    return OmegaConf.to_container(cfg[group], resolve=resolve)  # type: ignore[return-value]


def load_model_config(
    name: str, profile: str, task: str | None = None, dataset: str | None = None
) -> dict[str, Any]:
    """The `model:` group as `python -m src.run [task=<task>] [dataset=<dataset>] model=<name>
    profile=<profile>` composes it (conf/model_profile/<name>_<profile>.yaml included; `task=nerf` also
    sets the NeRF dataset that `model.background` refers to; `dataset=volumetric` gives the KPCN family
    the sequences' one `radiance` branch and its `in_channels`, as the `unet_vs_kpcn` study trains it). A
    model whose class reads branches the default data lack (the U-Net KPCN: the sequences' `radiance`)
    is composed with the first `conf/dataset` that has them, so its `in_channels` are those of its data."""
    overrides = ([f"task={task}"] if task else []) + ([f"dataset={dataset}"] if dataset else [])
    overrides += [f"model={name}", f"profile={profile}"]
    model = _compose(overrides, "model")
    reads = set(getattr(resolve_target(model), "branches", ()))
    if not reads or reads <= set(_compose(overrides, "dataset").get("branches") or ()):
        return model
    for dataset in sorted(p.stem for p in (CONF_DIR / "dataset").glob("*.yaml")):
        data = _compose([*overrides, f"dataset={dataset}"], "dataset", resolve=False)
        if reads <= set(data.get("branches") or ()):
            return _compose([*overrides, f"dataset={dataset}"], "model")
    return model


def load_dataset_config(task: str, profile: str) -> dict[str, Any]:
    """The `dataset:` group as `python -m src.run task=<task> profile=<profile>` composes it (the task's
    default dataset, with its task profile's overrides)."""
    return _compose([f"task={task}", f"profile={profile}"], "dataset")


def load_task_config(task: str, profile: str) -> dict[str, Any]:
    """The `task:` group as `python -m src.run task=<task> profile=<profile>` composes it, unresolved (its
    run paths need a Hydra run)."""
    return _compose([f"task={task}", f"profile={profile}"], "task", resolve=False)
