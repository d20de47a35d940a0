"""Training loop of the learned denoisers (`stage=train`), on every denoising kind of data.

The kind of data (`dataset._target_`, `src/kinds/`) gives what differs: its training and validation
datasets (items of k frames; a still image is a sequence of one), the input features a checkpoint
records, the colour space its branches map back through, what the model is fitted to
(`src.objectives.terms`: the branches' losses for still images, reconstruction + temporal loss for
sequences) and the learning-rate schedule. The frames of a batch's samples are flattened into one
batch for the model (`flatten_frames`). Per step (every `log_every`) and per epoch, on train and
validation data, each logged loss is written: `{train,val}_loss_<name>`.

With `probe=True` the run is the feature-selection probe (Zhang et al. 2022, `src.train.feature_selection`):
every sample keeps a random subset of the candidate features (`dataset.feature_selection.subsets`:
`uniform_size`, a uniform subset size then a uniform subset of it, or `independent`, each dropped with
probability `dataset.feature_selection.dropout`), the others' channels set to their neutral values, so that
one network learns to denoise with any subset.

The loop itself (progress, checkpoints, resume, Ctrl-C) is the shared `src.train.loop.TrainingLoop`; the
data order of an epoch depends only on (seed, epoch), so a resumed run ends with the same weights.
"""

from __future__ import annotations

import functools
import logging
import math
from collections.abc import Iterator
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from torch.utils.data import DataLoader
from tqdm import tqdm

from src.data.volume_features import VOLUME_CANDIDATE_FEATURES
from src.models.denoise.base import Batch
from src.train import feature_selection as fs
from src.train.curves import write_curves
from src.train.device import autocast, autocast_dtype
from src.train.loop import Means, OnStep, TrainingLoop, run_training

log = logging.getLogger(__name__)

#: Batch entries that are not per-frame tensors (a sample's first frame and crop corner).
_SAMPLE_META = ("start", "corner")


def flatten_frames(batch: Batch) -> dict[str, torch.Tensor]:
    """(N, k, C, H, W) sample tensors as one (N*k, C, H, W) batch of frames."""
    return {k: v.flatten(0, 1) for k, v in batch.items() if k not in _SAMPLE_META}


def _to(batch: Batch, device: torch.device) -> dict[str, torch.Tensor]:
    return {k: v.to(device, non_blocking=True) for k, v in batch.items()}


def _autocast(device: torch.device, amp: bool):
    """bfloat16 autocast on CUDA when `amp` (mixed precision; bf16 needs no loss scaling); else fp32."""
    return autocast(device.type, autocast_dtype(amp, device))


class DenoiserTrainer(TrainingLoop):
    """Samples of k frames from the prepared data, epochs of the training split, validation after every
    epoch; what is fitted comes from the data kind `kind` (module docstring), which the task built."""

    def __init__(
        self, cfg: DictConfig, tracker, on_step: OnStep = None, probe: bool = False, *, kind: Any
    ) -> None:
        self.kind = kind
        self.unit = self.kind.sample_unit
        self.features = self.kind.features(cfg)
        self.train_data, self.val_data = self.kind.training_data(cfg, self.features)
        super().__init__(cfg, tracker, on_step, **self.kind.build_context(cfg, self.train_data))
        self.terms = self.kind.loss_terms(cfg, self.train_data)
        self.dropout = _FeatureDropout(cfg, self.features, self.kind.probe_key) if probe else None
        self.history: dict[str, float] = {}  # the last completed epoch's train/val losses

    def schedule_config(self):
        """The data kind's schedule (the sequences' own decay, else `task.train.schedule`)."""
        return self.kind.schedule(self.cfg)

    def losses(self, batch: Batch) -> dict[str, torch.Tensor]:
        """Every logged loss of one batch of n samples of k frames."""
        n, k = batch["color"].shape[:2]
        frames = flatten_frames(batch)
        if self.dropout is not None and self.model.training:
            key = self.dropout.key
            frames[key] = self.dropout(frames[key], n, k, self.pos.step)
        return self.losses_of_frames(frames, batch, n, k)

    def losses_of_frames(self, frames: Batch, batch: Batch, n: int, k: int) -> dict[str, torch.Tensor]:
        """The losses of the flattened `frames` of `batch`'s n samples of k frames."""
        return self.terms(self.model, frames, batch, n, k)

    def objective(self, losses: dict[str, Any]) -> Any:
        """What the optimiser minimises of `losses`."""
        return self.terms.objective(losses)

    def checkpoint_extra(self) -> dict[str, Any]:
        return {"features": self.features}

    def batches(self, epoch: int, skip: int = 0) -> Iterator[Batch]:
        return self._batches(self.train_data, epoch, skip)

    def _batches(self, data, epoch: int, skip: int = 0) -> Iterator[Batch]:
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
        """Mean losses over all validation samples (weighted by batch size)."""
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
        # the training clock at this point (`train_time_s`: batches and optimiser steps, not validation):
        # the x axis of the reports' quality-against-time curves
        clock = {"train_time_s": self.train_seconds}
        self.tracker.log_metrics({**metrics, **clock, "epoch": self.pos.epoch}, step=self.pos.step)
        self.curves.append({"step": self.pos.step, "epoch": self.pos.epoch, **metrics, **clock})
        write_curves(self.t.curves_file, self.curves)
        log.info(
            "epoch %d: train %s | val %s",
            self.pos.epoch,
            " ".join(f"{k}={v:.4f}" for k, v in train_losses.items()),
            " ".join(f"{k}={v:.4f}" for k, v in val_losses.items()),
        )
        self.history = metrics

    def extra_summary(self) -> dict[str, Any]:
        # Per epoch: the time claims compare models trained for different epochs (DPCN gets twice KPCN's
        # in the seed thesis, whose Table 6.1 gives hours for 40 epochs each).
        per_epoch = self.train_seconds / self.pos.epoch if self.pos.epoch else float("nan")
        return {"epochs": self.pos.epoch, "train_time_per_epoch_s": per_epoch, **self.history}


class _FeatureDropout:
    """The probe's random feature dropout on the input group `key`: per sample (all k frames alike), a
    random subset of the candidates kept, the start set always (`fs.keep_mask` under
    `dataset.feature_selection.subsets`), seeded by (seed, step), so that a resumed probe sees the same
    masks."""

    def __init__(self, cfg: DictConfig, features: list[str] | None, key: str) -> None:
        sel = cfg.dataset.feature_selection
        features = list(features or VOLUME_CANDIDATE_FEATURES)
        self.key = key
        self.slices = fs.feature_slices(features)
        names = [name for name, _ in self.slices]
        # keep_only: a one-line ConfigError if the start set names a feature the probe does not read.
        self.always = fs.keep_only(sel.start, names).nonzero().flatten().tolist()
        self.neutral = fs.neutral_values(features, OmegaConf.to_container(sel.neutral, resolve=True))
        self.p, self.seed, self.subsets = float(sel.dropout), int(cfg.seed), str(sel.subsets)

    def __call__(self, inputs: torch.Tensor, n: int, k: int, step: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + step)
        keep = fs.keep_mask(self.subsets, n, len(self.slices), self.p, generator, self.always)
        keep = keep.repeat_interleave(k, dim=0).to(inputs.device)
        return fs.drop_features(inputs, keep, self.slices, self.neutral.to(inputs.device), channel_axis=1)


def train_denoiser(cfg: DictConfig, tracker, kind: Any, on_step: OnStep = None) -> dict[str, Any]:
    """Train `cfg.model` on the data kind `kind`'s prepared data (`paths.prepared`); resume from
    `task.train.resume` when set."""
    logged = ("train_time_s", "param_count", "steps", "epochs", "train_time_per_epoch_s")
    return run_training(functools.partial(DenoiserTrainer, kind=kind), cfg, tracker, on_step, logged)
