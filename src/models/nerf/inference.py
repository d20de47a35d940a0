"""Rendering any number of rays with a trained radiance field, a chunk at a time (evaluation, benchmark)."""

from __future__ import annotations

import torch
from torch import Tensor

from src.errors import ConfigError, DataError
from src.models.nerf.models import RAY_KEYS, NerfModelBase, Rays


def render_rays_chunked(
    model: NerfModelBase,
    rays: Rays,
    chunk: int,
    randomized: bool = False,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """Render any number of rays `chunk` at a time (no_grad; Ref-NeRF still differentiates its density
    internally for the normals, then detaches). Returns the fine level's `model.render_keys`, each
    (N, ...) concatenated on the CPU."""
    missing = [k for k in RAY_KEYS if k not in rays]
    if missing:
        raise DataError(f"rays: missing {missing}; expected keys {list(RAY_KEYS)}")
    if chunk < 1:
        raise ConfigError(f"chunk: expected a positive integer, got {chunk!r}")
    param = next(model.parameters())
    n = rays["origins"].shape[0]
    pieces: dict[str, list[Tensor]] = {k: [] for k in model.render_keys}
    with torch.no_grad():
        for start in range(0, n, chunk):
            batch = {k: rays[k][start : start + chunk].to(param.device, param.dtype) for k in RAY_KEYS}
            fine = model(batch, randomized=randomized, generator=generator)[-1]
            for k in model.render_keys:
                pieces[k].append(fine[k].detach().cpu())
    return {k: torch.cat(v) for k, v in pieces.items()}
