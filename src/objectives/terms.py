"""What a denoiser is fitted to, per kind of data (the kind picks one: `src/kinds/`). Each is called on a
batch's frames (the k frames of its N samples flattened, `src.models.denoise.base`) and returns every
logged loss; `objective` says which of them the optimiser minimises.

- `BranchLosses` (still images; Bako et al. 2017, the Zagreb thesis Sec. 5): a branch model's outputs are
  fitted to their transformed targets, objective = loss(diffuse) + loss(specular); the final colour,
  rebuilt with the data's colour space, is scored with the same loss for the logs only. A model that
  predicts colour directly is fitted on that colour against the reference. Logged: `diffuse`, `specular`,
  `color` (a colour model: `color`).
- `TemporalLosses` (sequences; Zhu et al. 2023, the Pixar/Disney talk): reconstruction on linear colour
  (SMAPE by default) plus `temporal_weight` times the temporal loss of the frame-to-frame differences in
  the stored radiance space (`src.objectives.temporal`). Logged: `color` (reconstruction), `temporal`,
  `total`.
"""

from __future__ import annotations

import functools
import operator
from typing import Any

import torch

from src.data.transforms import volume_transform
from src.errors import DataError
from src.models.denoise.base import Batch, ColorSpace, Denoiser, final_color
from src.objectives.losses import Loss
from src.objectives.temporal import temporal_loss


def component_losses(model: Denoiser, batch: Batch, loss: Loss, space: ColorSpace) -> dict[str, torch.Tensor]:
    """Loss of each of the model's outputs against its target (a branch against `<branch>_target`, colour
    against the reference), and of the final colour (rebuilt from the branches when the model predicts
    them) against the reference."""
    out = model(batch)
    targets = {**{b: f"{b}_target" for b in space.branches}, "color": "reference"}
    unknown = [key for key in out if key not in targets]
    if unknown:
        raise DataError(
            f"{type(model).__name__}.forward returned {unknown}; a denoiser returns some of {list(targets)}"
        )
    losses = {key: loss(value, batch[targets[key]]) for key, value in out.items()}
    if "color" not in losses:
        losses["color"] = loss(final_color(out, batch, space).float(), batch["reference"])
    return losses


def objective(losses: dict[str, Any]) -> Any:
    """What the optimiser minimises: the sum of the predicted branches' losses (diffuse + specular for a
    two-branch model, whose colour loss is only logged; the colour loss for a colour model)."""
    fitted = [v for k, v in losses.items() if k != "color"] or [losses["color"]]
    return functools.reduce(operator.add, fitted)


class BranchLosses:
    """Each output against its target; the optimiser minimises the branches' sum (module docstring)."""

    def __init__(self, loss: Loss, space: ColorSpace) -> None:
        self.loss, self.space = loss, space

    def __call__(self, model: Denoiser, frames: Batch, batch: Batch, n: int, k: int) -> dict[str, Any]:
        return component_losses(model, frames, self.loss, self.space)

    def objective(self, losses: dict[str, Any]) -> Any:
        return objective(losses)


class TemporalLosses:
    """Reconstruction on linear colour plus the weighted temporal term (module docstring)."""

    def __init__(
        self, loss: Loss, space: ColorSpace, *, weight: float, mode: str, warp: bool, transform: str
    ) -> None:
        self.loss, self.space = loss, space
        self.weight, self.mode, self.warp, self.transform = float(weight), str(mode), bool(warp), transform

    def __call__(self, model: Denoiser, frames: Batch, batch: Batch, n: int, k: int) -> dict[str, Any]:
        output = final_color(model(frames), frames, self.space).float()
        output = output.view(n, k, *output.shape[1:])
        reconstruction = self.loss(output, batch["reference"])
        motion = batch["motion"] if self.warp else None
        target = batch[f"{self.space.branches[0]}_target"]
        temporal = temporal_loss(volume_transform(output, self.transform), target, self.mode, motion)
        total = reconstruction + self.weight * temporal
        return {"color": reconstruction, "temporal": temporal, "total": total}

    def objective(self, losses: dict[str, Any]) -> Any:
        return losses["total"]
