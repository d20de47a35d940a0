"""Training checkpoints: one self-contained file per save, written atomically.

A checkpoint holds the model and optimiser state, the position in training (epoch, batch within the epoch,
global step), the RNG states, the MLflow run id (so a resumed run continues the same MLflow run), the
digest of the config that wrote it (so a job starting again in its folder continues only its own) and the
model config it was built from (so loading it into a different architecture fails with a clear message
instead of a wall of state_dict key errors).
"""

from __future__ import annotations

import os
import random
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig

from src.errors import DataError
from src.io.atomic import atomic_path
from src.models.nerf.builders import upgrade_legacy_encodings
from src.provenance import continued_in_place

#: Keys every checkpoint carries; a file without them is not one of ours.
CHECKPOINT_KEYS = ("format", "model_config", "model", "optimizer", "epoch", "batch_in_epoch", "step")
FORMAT = "nrbench-checkpoint-v1"
FINAL_NAME = "final.pt"
LAST_NAME = "last.pt"


def checkpoint_run_id(path: str | os.PathLike[str]) -> str | None:
    """The MLflow run that wrote a checkpoint (`mlflow_run_id`; None for one written without tracking),
    without reading its weights: a resumed training or a later evaluation logs into that run."""
    return load_checkpoint(path, mmap=True).get("mlflow_run_id")


def written_digest(path: str | os.PathLike[str]) -> str | None:
    """The digest of the config that wrote checkpoint `path` (None from a version that recorded none),
    without reading its weights."""
    return load_checkpoint(path, mmap=True).get("config_digest")


def resumable_checkpoint(cfg: DictConfig) -> str | None:
    """The checkpoint a training of `cfg` continues: `task.train.resume` when set; else, with `auto_resume`,
    `last.pt` in `task.train.checkpoint_dir` when the same configuration wrote it (a requeued job in its
    own run folder); else None (start over)."""
    train = cfg.task.train
    if train.get("resume"):
        return str(train.resume)
    path = Path(train.checkpoint_dir) / LAST_NAME
    return str(path) if continued_in_place(cfg, path, written_digest) else None


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any]) -> None:
    """Write `state` (must contain CHECKPOINT_KEYS except `format`) atomically: a crash mid-save leaves
    the previous checkpoint intact."""
    with atomic_path(path) as tmp:
        torch.save({"format": FORMAT, **state}, tmp)


def load_checkpoint(path: str | os.PathLike[str], mmap: bool = False) -> dict[str, Any]:
    """Read a checkpoint (a file, or a directory holding `last.pt`); a missing, truncated or foreign file
    raises a one-line DataError naming it. `mmap`: map the tensors' storage from the file instead of
    reading it (what only needs the small entries, such as the run id, reads no weights)."""
    path = Path(path)
    if path.is_dir():
        path = path / LAST_NAME
    if not path.is_file():
        raise DataError(f"{path}: no checkpoint there")
    try:
        # weights_only=False: the optimiser state and RNG states are plain containers, but numpy RNG
        # state is not allow-listed; checkpoints are the user's own files, not downloaded ones.
        state = torch.load(path, map_location="cpu", weights_only=False, mmap=mmap)
    except Exception as e:  # torch raises several types for a corrupt zip / pickle
        raise DataError(
            f"{path}: not a readable checkpoint ({type(e).__name__}: {e})".replace("\n", " ")
        ) from e
    missing = [k for k in CHECKPOINT_KEYS if not isinstance(state, dict) or k not in state]
    if missing or state.get("format") != FORMAT:
        raise DataError(f"{path}: not an nrbench checkpoint (missing {missing or ['format ' + FORMAT]})")
    return state


#: Checkpoints written before methods were built from `model._target_` named the builder by
#: `model.architecture` (denoisers) or by `model.name` (radiance fields, `family: nerf`): the target that
#: builds the same network, so that those checkpoints still load.
LEGACY_TARGETS = {
    "conv_stack": "src.models.denoise.models.conv_stack_denoiser",
    "residual": "src.models.denoise.models.residual_denoiser",
}
LEGACY_NERF_TARGETS = {
    name: f"src.models.nerf.builders.{name}_model" for name in ("nerf", "mipnerf", "refnerf")
}


#: Before one batch contract served still images and sequences (issue 31), the sequences' KPCN family had
#: builders of its own (one `net` over `inputs`, and a `transform` key); today they are the still images'
#: builders with the sequences' one branch.
FRAME_TARGETS = {
    "src.models.denoise.frame_models.frame_conv_stack_denoiser": LEGACY_TARGETS["conv_stack"],
    "src.models.denoise.frame_models.frame_residual_denoiser": LEGACY_TARGETS["residual"],
}
#: The branches of a KPCN-family checkpoint that predates `model.branches`: the still images' two.
STILL_BRANCHES = ["diffuse", "specular"]


def _upgraded(model_config: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's model config in today's keys (`architecture` or a NeRF name -> `_target_`; a NeRF's
    flat encoding keys -> its encoding sub-configs, `upgrade_legacy_encodings`; the sequences' frame
    builders -> the branch builders with `branches: [radiance]`; a KPCN-family config without
    `branches` -> the still images' two)."""
    if "_target_" not in model_config:
        if model_config.get("family") == "nerf":
            target = LEGACY_NERF_TARGETS.get(model_config.get("name"))
        else:
            target = LEGACY_TARGETS.get(model_config.get("architecture"))
        old = {k: v for k, v in model_config.items() if k != "architecture"}
        model_config = model_config if target is None else {"_target_": target, **old}
    model_config = upgrade_legacy_encodings(model_config)
    target = model_config.get("_target_")
    if target in FRAME_TARGETS:
        kept = {k: v for k, v in model_config.items() if k not in ("_target_", "transform")}
        return {"_target_": FRAME_TARGETS[target], **kept, "branches": ["radiance"]}
    if target in LEGACY_TARGETS.values() and "branches" not in model_config:
        return {**model_config, "branches": STILL_BRANCHES}
    return model_config


def _upgraded_weights(state: dict[str, Any]) -> dict[str, Any]:
    """A checkpoint's weights under today's names (a frame builder's `net.*` -> `radiance_net.*`)."""
    if state["model_config"].get("_target_") not in FRAME_TARGETS:
        return state["model"]
    return {(f"radiance_{k}" if k.startswith("net.") else k): v for k, v in state["model"].items()}


def check_model_config(
    state: dict[str, Any], model_cfg: dict[str, Any], path: str | os.PathLike[str]
) -> None:
    """The checkpoint was trained with the same architecture as `model_cfg` (ignoring the name)."""
    saved = {k: v for k, v in _upgraded(state["model_config"]).items() if k != "name"}
    wanted = {k: v for k, v in _upgraded(dict(model_cfg)).items() if k != "name"}
    diff = sorted(k for k in saved.keys() | wanted.keys() if saved.get(k) != wanted.get(k))
    if diff:
        pairs = ", ".join(f"model.{k}: {saved.get(k)!r} in checkpoint vs {wanted.get(k)!r}" for k in diff)
        raise DataError(f"{path}: checkpoint built for a different model ({pairs})")


def load_weights(model: torch.nn.Module, model_cfg: dict[str, Any], path: str | os.PathLike[str]) -> dict:
    """Load checkpoint `path`'s weights into `model` after checking it was built for `model_cfg`;
    returns the checkpoint."""
    state = load_checkpoint(path)
    check_model_config(state, model_cfg, path)
    model.load_state_dict(_upgraded_weights(state))
    return state


def rng_states() -> dict[str, Any]:
    """Every generator `seed_everything` seeds: torch's CPU one, each CUDA device's (NeRF's sample
    jitter draws on the device it trains on) and Python's."""
    return {
        "torch_rng": torch.get_rng_state(),
        "cuda_rng": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
        "python_rng": random.getstate(),
    }


def set_rng_states(state: dict[str, Any]) -> None:
    """Restore what `rng_states` saved (checkpoints from before `cuda_rng` / `python_rng` lack them)."""
    torch.set_rng_state(state["torch_rng"])
    if state.get("cuda_rng") is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda_rng"])
    if state.get("python_rng") is not None:
        random.setstate(state["python_rng"])


def training_state(trainer: Any, epoch: int, batch_in_epoch: int, step: int, **extra: Any) -> dict[str, Any]:
    """What both training loops checkpoint: model config, model, optimiser, position, training time,
    RNG states (the sample jitter draws from them), MLflow run id and the curves so far.

    `trainer` has `config_digest` (of its config: `config_digest`), `model_cfg`, `model`, `optimizer`,
    `train_seconds`, `tracker` and `curves`."""
    return {
        **extra,
        "model_config": trainer.model_cfg,
        "model": trainer.model.state_dict(),
        "optimizer": trainer.optimizer.state_dict(),
        "epoch": epoch,
        "batch_in_epoch": batch_in_epoch,
        "step": step,
        "train_seconds": trainer.train_seconds,
        **rng_states(),
        "mlflow_run_id": trainer.tracker.run_id,
        "curves": trainer.curves,
        "config_digest": trainer.config_digest,
    }


def restore_training_state(trainer: Any, path: str | os.PathLike[str]) -> dict[str, Any]:
    """Load checkpoint `path` into `trainer` (checked against its model config): model, optimiser, RNG
    states, training time and curves; returns the checkpoint for the caller's position fields."""
    state = load_weights(trainer.model, trainer.model_cfg, path)
    trainer.optimizer.load_state_dict(state["optimizer"])
    set_rng_states(state)
    trainer.train_seconds = float(state.get("train_seconds", 0.0))
    trainer.curves = list(state.get("curves", []))
    return state
