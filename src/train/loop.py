"""The one training loop every task shares (`stage=train`): position, progress bar, timing, checkpoints,
resume, Ctrl-C and the run summary. A task's trainer (`DenoiserTrainer`, `NerfTrainer`) subclasses
`TrainingLoop` and supplies only what differs: its batches, one optimiser step, what it logs after a
step and at the end of an epoch, and when training is done.

Position: `batch_in_epoch` batches of `epoch` are done, `step` optimiser steps in all. A task's batches
depend only on (seed, epoch, batch index) (a NeRF run is one epoch of `max_steps` batches), so resuming
replays the epoch's order and skips the batches already done: an interrupted and resumed run ends with
the same weights as an uninterrupted one.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import hydra
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from src.errors import ConfigError, one_line
from src.models.instantiate import build_method
from src.models.parameters import count_parameters
from src.provenance import config_digest
from src.train.checkpoint import (
    FINAL_NAME,
    LAST_NAME,
    restore_training_state,
    resumable_checkpoint,
    save_checkpoint,
    training_state,
)
from src.train.device import pick_device, seed_everything

log = logging.getLogger(__name__)

OnStep = Callable[[int], None] | None


@dataclass
class Position:
    """Where training is: `batch_in_epoch` batches of `epoch` are done, `step` optimiser steps in all."""

    epoch: int = 0
    batch_in_epoch: int = 0
    step: int = 0


class Means:
    """Sample-weighted running means of named values (the keys come from the first update)."""

    def __init__(self) -> None:
        self.totals: dict[str, float] = {}
        self.count = 0

    def add(self, values: dict[str, float], size: int) -> None:
        for key, value in values.items():
            self.totals[key] = self.totals.get(key, 0.0) + float(value) * size
        self.count += size

    def result(self) -> dict[str, float]:
        return {k: v / max(self.count, 1) for k, v in self.totals.items()}


class TrainingLoop:
    """Owns the model, optimiser, position, curves and checkpoints of one training run.

    A subclass calls `super().__init__` (device, seed, model from `cfg.model`, optimiser from
    `task.train.optimizer`) and implements `batches`, `train_step`, `done`, and optionally the hooks
    `after_step`, `end_epoch`, `before_training`, `progress`, `extra_summary` and `checkpoint_extra`.
    """

    #: What the progress bar counts (`progress` says how many).
    unit = "step"

    #: The `task.train` key holding the (initial) learning rate.
    lr_key = "lr"

    def __init__(self, cfg: DictConfig, tracker, on_step: OnStep = None, **build_context: Any) -> None:
        self.cfg, self.t, self.tracker, self.on_step = cfg, cfg.task.train, tracker, on_step
        self.device = pick_device(cfg.device)
        seed_everything(int(cfg.seed))
        self.model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
        self.config_digest = config_digest(cfg)  # every checkpoint records it (`resumable_checkpoint`)
        self.model = build_method(self.model_cfg, **build_context).to(self.device)
        self.lr = float(self.t[self.lr_key])
        self.optimizer = build_optimizer(self.t.optimizer, self.model.parameters(), self.lr)
        self.schedule = build_schedule(self.schedule_config())
        self.pos = Position()
        self.checkpoint_dir = Path(self.t.checkpoint_dir)
        self.train_seconds = 0.0
        self.curves: list[dict[str, float]] = []  # what curves.csv holds: one row per validation

    # -- what a task supplies -------------------------------------------------------------------------
    def schedule_config(self) -> DictConfig | None:
        """The learning-rate schedule's config (`task.train.schedule`; None: a constant rate)."""
        return self.t.get("schedule")

    def batches(self, epoch: int, skip: int) -> Iterator[Any]:
        """The batches of `epoch` after the first `skip`, in an order fixed by (seed, epoch)."""
        raise NotImplementedError

    def train_step(self, batch: Any) -> tuple[dict[str, float], int]:
        """One optimiser step; returns its logged values and the batch size."""
        raise NotImplementedError

    def done(self) -> bool:
        raise NotImplementedError

    def after_step(self, values: dict[str, float], size: int, bar: tqdm) -> None:
        """Progress and per-step logging (and any validation or checkpoint every N steps)."""

    def end_epoch(self, means: dict[str, float]) -> None:
        """Called with the epoch's mean train values when an epoch completes."""

    def before_training(self) -> None:
        """Called once before the first step of `fit` (e.g. to validate the initialisation)."""

    def progress(self) -> tuple[int, int]:
        """(total, done) in `unit`s, for the progress bar."""
        return int(self.t.max_steps), self.pos.step

    def total_steps(self) -> int:
        """The optimiser steps the whole run takes (what a schedule decays over)."""
        return int(self.t.max_steps)

    def extra_summary(self) -> dict[str, Any]:
        """Task-specific entries of the run summary `fit` returns."""
        return {}

    def checkpoint_extra(self) -> dict[str, Any]:
        """Task-specific entries of every checkpoint."""
        return {}

    # -- checkpoints ----------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        pos = self.pos
        return training_state(self, pos.epoch, pos.batch_in_epoch, pos.step, **self.checkpoint_extra())

    def save(self, name: str = LAST_NAME) -> Path:
        path = self.checkpoint_dir / name
        save_checkpoint(path, self.state())
        return path

    def restore(self, path: str) -> None:
        state = restore_training_state(self, path)
        self.pos = Position(state["epoch"], state["batch_in_epoch"], state["step"])
        self.tracker.skip_logged_after(self.pos.step)  # what a crash after this checkpoint logged
        log.info("resumed from %s at epoch %d, batch %d, step %d", path, *vars(self.pos).values())

    # -- the loop ---------------------------------------------------------------------------------------
    def stop_inside_epoch(self) -> bool:
        max_steps = self.t.max_steps
        return max_steps is not None and self.pos.step >= int(max_steps)

    def set_learning_rate(self) -> None:
        """The schedule's learning rate for the coming step (nothing to do without a schedule)."""
        if self.schedule is None:
            return
        lr = self.schedule(self.pos.step, lr_init=self.lr, max_steps=self.total_steps())
        for group in self.optimizer.param_groups:
            group["lr"] = lr

    def run_epoch(self, bar: tqdm) -> bool:
        """Train the rest of the current epoch, or until `max_steps`; True if the epoch completed.
        `train_seconds` counts fetching each batch and the optimiser step, not logging or validation."""
        means = Means()
        start = time.perf_counter()
        for batch in self.batches(self.pos.epoch, skip=self.pos.batch_in_epoch):
            self.set_learning_rate()
            values, size = self.train_step(batch)
            self.train_seconds += time.perf_counter() - start
            means.add(values, size)
            self.pos.batch_in_epoch += 1
            self.pos.step += 1
            self.after_step(values, size, bar)
            if self.on_step is not None:
                self.on_step(self.pos.step)
            if self.stop_inside_epoch():
                return False
            start = time.perf_counter()
        self.pos = Position(self.pos.epoch + 1, 0, self.pos.step)
        self.end_epoch(means.result())
        return True

    def fit(self) -> dict[str, Any]:
        """Train until `done`; checkpoint before the first step, after every epoch (or stop), on Ctrl-C and
        on a requeue's exit, then `final.pt`."""
        total, done = self.progress()
        name = self.model_cfg["name"]
        bar = tqdm(total=total, initial=min(done, total), desc=f"train {name}", unit=self.unit)
        try:
            if self.pos.step == 0:
                # The MLflow run id on disk from the start: a job requeued before its first epoch ends
                # continues this run instead of opening a second one.
                self.save()
            self.before_training()
            while not self.done():
                self.run_epoch(bar)
                self.save()
        except (KeyboardInterrupt, SystemExit):
            # Ctrl-C, or submitit's exit after it requeued the job (time-out, preemption): keep what was
            # done since the last checkpoint; the job continues from exactly here.
            self.save()
            raise
        finally:
            bar.close()
        final = self.save(FINAL_NAME)
        return {
            "checkpoint": str(final),
            "steps": self.pos.step,
            "train_time_s": self.train_seconds,
            "param_count": count_parameters(self.model),
            **self.extra_summary(),
        }


def _built(key: str, build: Callable[[], Any]) -> Any:
    """`build()` of the `task.train.<key>` node; any error (Hydra wraps import and argument errors in
    several exception types) as one ConfigError line naming the key."""
    try:
        return build()
    except Exception as err:
        raise ConfigError(f"task.train.{key}: {one_line(err)}") from err


def build_optimizer(node: DictConfig, parameters, lr: float) -> torch.optim.Optimizer:
    """`task.train.optimizer` (a `_target_` with `_partial_: true`, e.g. torch.optim.Adam) on `parameters`
    with learning rate `lr` (the task's own key: one place to set and sweep it)."""
    return _built("optimizer", lambda: hydra.utils.instantiate(node, _convert_="all")(parameters, lr=lr))


def build_schedule(node: DictConfig | None) -> Callable[..., float] | None:
    """`task.train.schedule` (a `_target_` with `_partial_: true`, called as (step, lr_init=, max_steps=)),
    or None for a constant learning rate."""
    return (
        None if node is None else _built("schedule", lambda: hydra.utils.instantiate(node, _convert_="all"))
    )


def run_training(
    trainer_class: Callable[..., TrainingLoop],
    cfg: DictConfig,
    tracker,
    on_step: OnStep,
    logged: tuple[str, ...],
) -> dict[str, Any]:
    """Build a trainer (`trainer_class(cfg, tracker, on_step)`: a class, or one with its other arguments
    bound), resume from `resumable_checkpoint(cfg)` when there is one, fit, log the summary's `logged`
    keys."""
    trainer = trainer_class(cfg, tracker, on_step)
    checkpoint = resumable_checkpoint(cfg)
    if checkpoint:
        trainer.restore(checkpoint)
    summary = trainer.fit()
    tracker.log_metrics({k: summary[k] for k in logged}, step=summary["steps"])
    return summary
