"""Training loop for the learned denoisers (`stage=train`).

The objective is the sum of the losses of what the model predicts, each against its target
(`TARGETS`): following the seed thesis, a two-branch model's diffuse and specular outputs are fitted to
their transformed targets (objective = loss(diffuse) + loss(specular)) and the final colour, rebuilt
with the inverse transform, is scored with the same loss for the logs only; a model that predicts colour
directly (one branch) is fitted on that colour against the reference. Per step (every `log_every`) and
per epoch, on train and validation patches, each loss is logged: `{train,val}_loss_{diffuse,specular,
color}` for a two-branch model, `{train,val}_loss_color` for a colour model.

The loop itself (progress, checkpoints, resume, Ctrl-C) is the shared `src.train.loop.TrainingLoop`; the
data order of an epoch depends only on (seed, epoch), so a resumed run ends with the same weights.
"""

from __future__ import annotations

import functools
import logging
import math
import operator
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig
from torch.utils.data import DataLoader
from tqdm import tqdm

from src.data.denoise_dataset import PatchShardDataset, selected_whitening
from src.data.features import input_features
from src.errors import DataError
from src.models.denoise.base import Batch, Denoiser, final_color
from src.train.curves import write_curves
from src.train.device import autocast, autocast_dtype
from src.train.loop import Means, OnStep, TrainingLoop, run_training
from src.train.losses import Loss, get_loss

log = logging.getLogger(__name__)

#: A model output -> the batch entry it is fitted to.
TARGETS = {"diffuse": "diffuse_target", "specular": "specular_target", "color": "reference"}


def component_losses(model: Denoiser, batch: Batch, loss: Loss, eps: float) -> dict[str, torch.Tensor]:
    """Loss of each of the model's outputs against its target (`TARGETS`), and of the final colour
    (rebuilt from the branches when the model predicts them) against the reference."""
    out = model(batch)
    unknown = [key for key in out if key not in TARGETS]
    if unknown:
        raise DataError(
            f"{type(model).__name__}.forward returned {unknown}; a denoiser returns some of {list(TARGETS)}"
        )
    losses = {key: loss(value, batch[TARGETS[key]]) for key, value in out.items()}
    if "color" not in losses:
        losses["color"] = loss(final_color(out, batch, eps).float(), batch["reference"])
    return losses


def objective(losses: dict[str, Any]) -> Any:
    """What the optimiser minimises: the sum of the predicted outputs' losses (diffuse + specular for a
    two-branch model, whose colour loss is only logged; the colour loss for a colour model)."""
    fitted = [losses[k] for k in ("diffuse", "specular") if k in losses] or [losses["color"]]
    return functools.reduce(operator.add, fitted)


def _to(batch: Batch, device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


def _autocast(device: torch.device, amp: bool):
    """bfloat16 autocast on CUDA when `amp` (mixed precision; bf16 needs no loss scaling); else fp32."""
    return autocast(device.type, autocast_dtype(amp, device))


class DenoiserTrainer(TrainingLoop):
    """Patches from the prepared shards, epochs of the training split, validation after every epoch."""

    unit = "patch"

    def __init__(self, cfg: DictConfig, tracker, on_step: OnStep = None) -> None:
        self.features = self.configured_features(cfg)
        self.train_data, self.val_data = self.datasets(cfg)
        super().__init__(cfg, tracker, on_step, **self.build_context(cfg))
        self.eps = float(cfg.task.preprocess.eps_albedo)
        self.loss = get_loss(self.t.loss)
        self.history: dict[str, float] = {}  # the last completed epoch's train/val losses

    # -- what the volumetric trainer (`src.train.sequence_trainer`) replaces -------------------------------
    def configured_features(self, cfg: DictConfig) -> list[str] | None:
        """The input features of this run (what its checkpoint records)."""
        return input_features(cfg)

    def datasets(self, cfg: DictConfig) -> tuple[Any, Any]:
        """The train and validation patch datasets."""
        data = {"seed": int(cfg.seed), "features": self.features}
        prepared = Path(cfg.paths.prepared)
        return (
            PatchShardDataset(prepared, "train", shuffle=True, **data),
            PatchShardDataset(prepared, "val", shuffle=False, **data),
        )

    def build_context(self, cfg: DictConfig) -> dict[str, Any]:
        """What the model's builder gets besides its config: the whitening statistics of its inputs."""
        if not cfg.model.get("whiten"):
            return {"whitening": None}
        prepared = Path(cfg.paths.prepared)
        return {"whitening": selected_whitening(prepared / "whitening.json", self.train_data.select)}

    def losses(self, batch: Batch) -> dict[str, torch.Tensor]:
        """Every logged loss of one batch (`component_losses`)."""
        return component_losses(self.model, batch, self.loss, self.eps)

    def objective(self, losses: dict[str, Any]) -> Any:
        """What the optimiser minimises of `losses` (`objective`)."""
        return objective(losses)

    def checkpoint_extra(self) -> dict[str, Any]:
        return {"features": self.features}

    def batches(self, epoch: int, skip: int = 0) -> Iterator[Batch]:
        return self._batches(self.train_data, epoch, skip)

    def _batches(self, data: PatchShardDataset, epoch: int, skip: int = 0) -> Iterator[Batch]:
        data.set_epoch(epoch)
        loader = DataLoader(data, batch_size=int(self.t.batch_size), num_workers=int(self.t.num_workers))
        for i, batch in enumerate(loader):
            if i >= skip:
                yield _to(batch, self.device)

    def done(self) -> bool:
        return self.pos.epoch >= int(self.t.epochs) or self.stop_inside_epoch()

    def total_steps(self) -> int:
        if self.t.max_steps is not None:
            return int(self.t.max_steps)
        return int(self.t.epochs) * math.ceil(len(self.train_data) / int(self.t.batch_size))

    def progress(self) -> tuple[int, int]:
        per_epoch = len(self.train_data)
        done = per_epoch * self.pos.epoch + self.pos.batch_in_epoch * int(self.t.batch_size)
        return per_epoch * int(self.t.epochs), done

    def train_step(self, batch: Batch) -> tuple[dict[str, float], int]:
        self.model.train()
        with _autocast(self.device, bool(self.t.amp)):
            losses = self.losses(batch)
        self.optimizer.zero_grad(set_to_none=True)
        self.objective(losses).backward()
        self.optimizer.step()
        return {k: float(v.detach()) for k, v in losses.items()}, len(batch["color"])

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Mean losses over all validation patches (weighted by batch size)."""
        self.model.eval()
        means = Means()
        for batch in self._batches(self.val_data, epoch=0):
            with _autocast(self.device, bool(self.t.amp)):
                means.add(self.losses(batch), len(batch["color"]))
        return means.result()

    def after_step(self, values: dict[str, float], size: int, bar: tqdm) -> None:
        bar.update(size)
        bar.set_postfix(step=self.pos.step, loss=f"{self.objective(values):.4f}")
        if self.pos.step % int(self.t.log_every) == 0:
            self.tracker.log_metrics(
                {f"train_step_loss_{k}": v for k, v in values.items()}, step=self.pos.step
            )

    def end_epoch(self, train_losses: dict[str, float]) -> None:
        val_losses = self.validate()
        metrics = {f"train_loss_{k}": v for k, v in train_losses.items()}
        metrics |= {f"val_loss_{k}": v for k, v in val_losses.items()}
        self.tracker.log_metrics({**metrics, "epoch": self.pos.epoch}, step=self.pos.step)
        self.curves.append({"step": self.pos.step, "epoch": self.pos.epoch, **metrics})
        write_curves(self.t.curves_file, self.curves)
        log.info(
            "epoch %d: train %s | val %s",
            self.pos.epoch,
            " ".join(f"{k}={v:.4f}" for k, v in train_losses.items()),
            " ".join(f"{k}={v:.4f}" for k, v in val_losses.items()),
        )
        self.history = metrics

    def extra_summary(self) -> dict[str, Any]:
        return {"epochs": self.pos.epoch, **self.history}


def train_denoiser(cfg: DictConfig, tracker, on_step: OnStep = None) -> dict[str, Any]:
    """Train `cfg.model` on `cfg.paths.prepared`; resume from `task.train.resume` when set."""
    logged = ("train_time_s", "param_count", "steps", "epochs")
    return run_training(DenoiserTrainer, cfg, tracker, on_step, logged)
