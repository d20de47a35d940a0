"""Training loop for the learned denoisers (`stage=train`).

The objective is the sum of the losses of what the model predicts, each against its target
(`TARGETS`): following the seed thesis, a two-branch model's diffuse and specular outputs are fitted to
their transformed targets (objective = loss(diffuse) + loss(specular)) and the final colour, rebuilt
with the inverse transform, is scored with the same loss for the logs only; a model that predicts colour
directly (one branch) is fitted on that colour against the reference. Per step (every `log_every`) and
per epoch, on train and validation patches, each loss is logged: `{train,val}_loss_{diffuse,specular,
color}` for a two-branch model, `{train,val}_loss_color` for a colour model.

Resume: a checkpoint records (epoch, batch within the epoch, step). The data order of an epoch depends only
on (seed, epoch), so resuming replays the epoch's order and skips the batches already done: an interrupted
and resumed run ends with the same weights as an uninterrupted one.
"""

from __future__ import annotations

import functools
import logging
import operator
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader
from tqdm import tqdm

from src.data.denoise_dataset import PatchShardDataset, selected_whitening
from src.data.features import input_features
from src.errors import DataError
from src.models.denoise.base import Batch, Denoiser, final_color
from src.models.denoise.summary import count_parameters
from src.models.instantiate import build_method
from src.train.checkpoint import (
    FINAL_NAME,
    LAST_NAME,
    restore_training_state,
    save_checkpoint,
    training_state,
)
from src.train.curves import write_curves
from src.train.device import pick_device, seed_everything
from src.train.losses import Loss, get_loss

log = logging.getLogger(__name__)

#: A model output -> the batch entry it is fitted to.
TARGETS = {"diffuse": "diffuse_target", "specular": "specular_target", "color": "reference"}


@dataclass
class Position:
    """Where training is: `batch_in_epoch` batches of `epoch` are done, `step` optimiser steps in all."""

    epoch: int = 0
    batch_in_epoch: int = 0
    step: int = 0


def model_config(cfg: DictConfig) -> dict[str, Any]:
    return OmegaConf.to_container(cfg.model, resolve=True)


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


class Means:
    """Sample-weighted running means of named losses (the keys come from the first update)."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = {}
        self.count = 0

    def add(self, losses: dict[str, float], size: int) -> None:
        for key, value in losses.items():
            self.totals[key] = self.totals.get(key, 0.0) + float(value) * size
        self.count += size

    def result(self) -> dict[str, float]:
        return {k: v / max(self.count, 1) for k, v in self.totals.items()}


def _to(batch: Batch, device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


def _autocast(device: torch.device, enabled: bool):
    """bfloat16 autocast on CUDA (mixed precision; bf16 needs no loss scaling); a no-op on CPU."""
    return torch.autocast(
        device_type=device.type, dtype=torch.bfloat16, enabled=enabled and device.type == "cuda"
    )


class Trainer:
    """Owns the model, optimiser, data and position of one training run."""

    def __init__(self, cfg: DictConfig, tracker, on_step: Callable[[int], None] | None = None) -> None:
        t = cfg.task.train
        self.cfg, self.t, self.tracker, self.on_step = cfg, t, tracker, on_step
        self.device = pick_device(cfg.device)
        self.eps = float(cfg.task.preprocess.eps_albedo)
        self.loss = get_loss(t.loss)
        self.model_cfg = model_config(cfg)
        self.features = input_features(cfg)
        seed_everything(int(cfg.seed))
        prepared = Path(cfg.paths.prepared)
        data = {"seed": int(cfg.seed), "features": self.features}
        self.train_data = PatchShardDataset(prepared, "train", shuffle=True, **data)
        self.val_data = PatchShardDataset(prepared, "val", shuffle=False, **data)
        whitening = (
            selected_whitening(prepared / "whitening.json", self.train_data.select)
            if self.model_cfg.get("whiten")
            else None
        )
        self.model = build_method(self.model_cfg, whitening=whitening).to(self.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=float(t.lr))
        self.pos = Position()
        self.checkpoint_dir = Path(t.checkpoint_dir)
        self.train_seconds = 0.0
        self.curves: list[dict[str, float]] = []  # one row per epoch: step, epoch, train/val losses

    # -- checkpoints ---------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        return training_state(
            self, self.pos.epoch, self.pos.batch_in_epoch, self.pos.step, features=self.features
        )

    def save(self, name: str = LAST_NAME) -> Path:
        path = self.checkpoint_dir / name
        save_checkpoint(path, self.state())
        return path

    def restore(self, path: str) -> None:
        state = restore_training_state(self, path)
        self.pos = Position(state["epoch"], state["batch_in_epoch"], state["step"])
        log.info("resumed from %s at epoch %d, batch %d, step %d", path, *vars(self.pos).values())

    # -- loop ----------------------------------------------------------------------------------------
    def _batches(self, data: PatchShardDataset, epoch: int, skip: int = 0) -> Iterator[Batch]:
        data.set_epoch(epoch)
        loader = DataLoader(data, batch_size=int(self.t.batch_size), num_workers=int(self.t.num_workers))
        for i, batch in enumerate(loader):
            if i >= skip:
                yield _to(batch, self.device)

    def _done(self) -> bool:
        max_steps = self.t.max_steps
        return self.pos.epoch >= int(self.t.epochs) or (max_steps is not None and self.pos.step >= max_steps)

    def train_step(self, batch: Batch) -> dict[str, float]:
        self.model.train()
        with _autocast(self.device, bool(self.t.amp)):
            losses = component_losses(self.model, batch, self.loss, self.eps)
        self.optimizer.zero_grad(set_to_none=True)
        objective(losses).backward()
        self.optimizer.step()
        return {k: float(v.detach()) for k, v in losses.items()}

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Mean losses over all validation patches (weighted by batch size)."""
        self.model.eval()
        means = Means()
        for batch in self._batches(self.val_data, epoch=0):
            with _autocast(self.device, bool(self.t.amp)):
                means.add(component_losses(self.model, batch, self.loss, self.eps), len(batch["color"]))
        return means.result()

    def run_epoch(self, bar: tqdm) -> dict[str, float] | None:
        """Train the rest of the current epoch (or until max_steps); returns the epoch's mean train
        losses if the epoch finished, None if training stopped inside it."""
        means = Means()
        start = time.perf_counter()
        for batch in self._batches(self.train_data, self.pos.epoch, skip=self.pos.batch_in_epoch):
            losses = self.train_step(batch)
            size = len(batch["color"])
            means.add(losses, size)
            self.pos.batch_in_epoch += 1
            self.pos.step += 1
            self._after_step(losses, size, bar)
            if self.t.max_steps is not None and self.pos.step >= self.t.max_steps:
                self.train_seconds += time.perf_counter() - start
                return None
        self.train_seconds += time.perf_counter() - start
        self.pos = Position(self.pos.epoch + 1, 0, self.pos.step)
        return means.result()

    def _after_step(self, losses: dict[str, float], size: int, bar: tqdm) -> None:
        bar.update(size)
        bar.set_postfix(step=self.pos.step, loss=f"{objective(losses):.4f}")
        if self.pos.step % int(self.t.log_every) == 0:
            self.tracker.log_metrics(
                {f"train_step_loss_{k}": v for k, v in losses.items()}, step=self.pos.step
            )
        if self.on_step is not None:
            self.on_step(self.pos.step)

    def fit(self) -> dict[str, Any]:
        """Train until `epochs` (or `max_steps`); checkpoint after every epoch and at the end."""
        epochs = int(self.t.epochs)
        total = len(self.train_data) * epochs
        done = len(self.train_data) * self.pos.epoch + self.pos.batch_in_epoch * int(self.t.batch_size)
        bar = tqdm(
            total=total, initial=min(done, total), desc=f"train {self.model_cfg['name']}", unit="patch"
        )
        history: dict[str, float] = {}
        try:
            while not self._done():
                train_losses = self.run_epoch(bar)
                if train_losses is not None:
                    history = self._end_epoch(train_losses)
                self.save()
        except KeyboardInterrupt:
            # Keep what was done since the last checkpoint; resume continues from exactly here.
            self.save()
            raise
        finally:
            bar.close()
        final = self.save(FINAL_NAME)
        return {
            "checkpoint": str(final),
            "epochs": self.pos.epoch,
            "steps": self.pos.step,
            "train_time_s": self.train_seconds,
            "param_count": count_parameters(self.model),
            **history,
        }

    def _end_epoch(self, train_losses: dict[str, float]) -> dict[str, float]:
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
        return metrics


def train_denoiser(cfg: DictConfig, tracker, on_step: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Train `cfg.model` on `cfg.paths.prepared`; resume from `task.train.resume` when set."""
    trainer = Trainer(cfg, tracker, on_step)
    if cfg.task.train.resume:
        trainer.restore(cfg.task.train.resume)
    summary = trainer.fit()
    tracker.log_metrics(
        {k: summary[k] for k in ("train_time_s", "param_count", "steps", "epochs")}, step=summary["steps"]
    )
    return summary
