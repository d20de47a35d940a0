"""Training on the volumetric sequences (`stage=train dataset=volumetric`, after Zhu et al. 2023, the
Pixar/Disney SIGGRAPH talk "Denoising Production Volumetric Rendering").

A training sample is one crop over k consecutive frames (`src.data.sequence_dataset`); its frames are
denoised independently (flattened into the batch: the frame-batch interface of
`src.models.denoise.base`, every model returning linear colour) and fitted with

    loss = reconstruction(output, reference) + temporal_weight * temporal(output, reference),

per `task.train.volumetric`: SMAPE on linear colour by default (the talk, after Vogels et al. 2018) and
the temporal loss on the frame-to-frame differences (`src.train.temporal`), taken in the stored radiance
space (`task.preprocess.volume_transform`: log-modulus by default, so that bright pixels do not drown the
term), with the learning rate decaying from `task.train.lr` (`task.train.volumetric.schedule`). Each term
is logged: `{train,val}_loss_color` (reconstruction), `_temporal` and `_total`.

With `probe=True` the run is the feature-selection probe (Zhang et al. 2022, `src.train.feature_selection`):
every sample drops each candidate feature with probability `task.feature_selection.dropout`, setting its
channels to their neutral values, so that one network learns to denoise with any subset.

Everything else (epochs over shuffled shards, validation, checkpoints, resume to identical weights) is the
still-image trainer's (`src.train.trainer.DenoiserTrainer`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf

from src.data.sequence_dataset import SequencePatchDataset
from src.data.volume_features import VOLUME_CANDIDATE_FEATURES, run_volume_features
from src.data.volume_shards import volume_transform
from src.models.denoise.base import Batch
from src.train import feature_selection as fs
from src.train.loop import OnStep, build_schedule, run_training
from src.train.losses import get_loss
from src.train.temporal import temporal_loss
from src.train.trainer import DenoiserTrainer

#: Batch entries that are not per-frame tensors (a sample's first frame and crop corner).
_SAMPLE_META = ("start", "corner")


def flatten_frames(batch: Batch) -> dict[str, torch.Tensor]:
    """(N, k, C, H, W) sample tensors as one (N*k, C, H, W) frame batch."""
    return {k: v.flatten(0, 1) for k, v in batch.items() if k not in _SAMPLE_META}


class SequenceTrainer(DenoiserTrainer):
    """Samples of k frames; reconstruction + temporal loss; optional feature dropout (the probe)."""

    unit = "sample"

    def __init__(self, cfg: DictConfig, tracker, on_step: OnStep = None, probe: bool = False) -> None:
        super().__init__(cfg, tracker, on_step)
        v = self.t.volumetric
        self.loss = get_loss(v.loss)
        if v.get("schedule") is not None:
            self.schedule = build_schedule(v.schedule)
        self.temporal_weight, self.temporal_mode = float(v.temporal_weight), str(v.temporal_mode)
        self.warp = bool(v.temporal_warp)
        self.transform = self.train_data.volume_transform
        self.dropout = _FeatureDropout(cfg, self.features) if probe else None

    def configured_features(self, cfg: DictConfig) -> list[str] | None:
        return run_volume_features(cfg)

    def datasets(self, cfg: DictConfig) -> tuple[Any, Any]:
        data = {"seed": int(cfg.seed), "features": self.features}
        prepared = Path(cfg.paths.prepared)
        return (
            SequencePatchDataset(prepared, "train", shuffle=True, **data),
            SequencePatchDataset(prepared, "val", shuffle=False, **data),
        )

    def build_context(self, cfg: DictConfig) -> dict[str, Any]:
        return {}

    def losses(self, batch: Batch) -> dict[str, torch.Tensor]:
        n, k = batch["inputs"].shape[:2]
        frames = flatten_frames(batch)
        if self.dropout is not None and self.model.training:
            frames["inputs"] = self.dropout(frames["inputs"], n, k, self.pos.step)
        return self.losses_of_frames(frames, batch, n, k)

    def losses_of_frames(self, frames: Batch, batch: Batch, n: int, k: int) -> dict[str, torch.Tensor]:
        """The losses of the flattened `frames` of `batch`'s n samples of k frames."""
        output = self.model(frames)["color"].float()
        output = output.view(n, k, *output.shape[1:])
        reconstruction = self.loss(output, batch["reference"])
        motion = batch["motion"] if self.warp else None
        temporal = temporal_loss(
            volume_transform(output, self.transform), batch["target"], self.temporal_mode, motion
        )
        total = reconstruction + self.temporal_weight * temporal
        return {"color": reconstruction, "temporal": temporal, "total": total}

    def objective(self, losses: dict[str, Any]) -> Any:
        return losses["total"]


class _FeatureDropout:
    """The probe's random feature dropout: per sample (all k frames alike), each candidate but the start
    set dropped with probability `task.feature_selection.dropout`, seeded by (seed, step), so that a
    resumed probe sees the same masks."""

    def __init__(self, cfg: DictConfig, features: list[str] | None) -> None:
        sel = cfg.task.feature_selection
        features = list(features or VOLUME_CANDIDATE_FEATURES)
        self.slices = fs.feature_slices(features)
        names = [name for name, _ in self.slices]
        # keep_only: a one-line ConfigError if the start set names a feature the probe does not read.
        self.always = fs.keep_only(sel.start, names).nonzero().flatten().tolist()
        self.neutral = fs.neutral_values(features, OmegaConf.to_container(sel.neutral, resolve=True))
        self.p, self.seed = float(sel.dropout), int(cfg.seed)

    def __call__(self, inputs: torch.Tensor, n: int, k: int, step: int) -> torch.Tensor:
        generator = torch.Generator().manual_seed(self.seed * 1_000_003 + step)
        keep = fs.random_keep_mask(n, len(self.slices), self.p, generator, self.always)
        keep = keep.repeat_interleave(k, dim=0).to(inputs.device)
        return fs.drop_features(inputs, keep, self.slices, self.neutral.to(inputs.device), channel_axis=1)


def train_sequence_denoiser(cfg: DictConfig, tracker, on_step: OnStep = None) -> dict[str, Any]:
    """Train `cfg.model` on the volumetric samples of `cfg.paths.prepared` (resuming when asked)."""
    logged = ("train_time_s", "param_count", "steps", "epochs")
    return run_training(SequenceTrainer, cfg, tracker, on_step, logged)
