"""Training losses on tensors, selected by name (`task.train.loss`).

The seeds train with L1 (Bako et al. 2017 found it converged to better results than L2 for HDR-transformed
targets); SMAPE and relMSE are the scale-invariant losses of later work (Vogels et al. 2018; Rousselle et
al. 2011 for relMSE). `eps` keeps the denominators away from zero in black regions.
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch

from src.errors import ConfigError
from src.models.instantiate import TARGET_KEY, resolve_target

Loss = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def l1(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """mean |pred - target|."""
    return (pred - target).abs().mean()


def l2(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """mean (pred - target)^2."""
    return (pred - target).square().mean()


def smape(pred: torch.Tensor, target: torch.Tensor, eps: float = 0.01) -> torch.Tensor:
    """Symmetric MAPE: mean |p - t| / (|p| + |t| + eps) (Vogels et al. 2018, Eq. 9)."""
    return ((pred - target).abs() / (pred.abs() + target.abs() + eps)).mean()


def relmse(pred: torch.Tensor, target: torch.Tensor, eps: float = 0.01) -> torch.Tensor:
    """Relative MSE: mean (p - t)^2 / (t^2 + eps); the target is a constant (no gradient through it)."""
    target = target.detach()
    return ((pred - target).square() / (target.square() + eps)).mean()


LOSSES: dict[str, Loss] = {"l1": l1, "l2": l2, "smape": smape, "relmse": relmse}


def get_loss(spec) -> Loss:
    """A loss by name (`LOSSES`), or a user's callable named by a `{_target_: ..., <keyword>: ...}`
    mapping, its other keys bound as keyword arguments
    (`{_target_: src.objectives.losses.smape, eps: 0.1}`)."""
    if isinstance(spec, str):
        if spec not in LOSSES:
            expected = f"expected one of {sorted(LOSSES)} or a {{_target_: ...}} mapping"
            raise ConfigError(f"task.train.loss={spec!r}: {expected}")
        return LOSSES[spec]
    loss = resolve_target(spec, "task.train.loss")
    options = {k: v for k, v in spec.items() if k != TARGET_KEY}
    return functools.partial(loss, **options) if options else loss
