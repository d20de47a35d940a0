"""What `stage=summary` and the benchmark report of a radiance field: parameters, samples per ray and MLP
FLOPs per ray."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torch import nn

from src.models.instantiate import model_dict
from src.models.nerf.models import LEVELS, NerfModelBase, RefNeRF
from src.models.parameters import count_parameters


def mlp_flops_per_sample(mlp: nn.Module) -> int:
    """2 x the multiply-accumulates of one MLP evaluation: every `nn.Linear` runs once per sample
    (bias additions, activations and encodings are not counted, the usual convention)."""
    return 2 * sum(m.in_features * m.out_features for m in mlp.modules() if isinstance(m, nn.Linear))


def nerf_mlp_flops_per_ray(model: NerfModelBase) -> dict[str, int]:
    """{"coarse", "fine", "total"}: MLP forward FLOPs per ray (samples x FLOPs per sample)."""
    samples = model.samples_per_level()
    flops = {
        level: s * mlp_flops_per_sample(model.mlp_for(i))
        for i, (level, s) in enumerate(zip(LEVELS, samples, strict=True))
    }
    flops["total"] = sum(flops.values())
    return flops


def nerf_model_summary(model: NerfModelBase, model_cfg: Mapping[str, Any]) -> str:
    """Architecture, parameter counts (total and per MLP), samples per ray and MLP FLOPs per ray."""
    cfg = model_dict(model_cfg)
    lines = [
        f"model: {cfg.get('name', model.name)} (family {cfg.get('family', 'nerf')}, learned True)",
        str(model),
    ]
    per = ", ".join(f"{label} {count_parameters(m):,}" for label, m in model.mlp_modules().items())
    lines.append(f"parameters: {count_parameters(model):,} ({per})")
    coarse, fine = model.samples_per_level()
    how = (
        f"{model.num_coarse_samples} coarse + {model.num_fine_samples} importance samples"
        if model.resample_padding is None
        else f"resampled with padding {model.resample_padding}"
    )
    lines.append(
        f"samples per ray: coarse {coarse}, fine {fine} ({how}); MLP evaluations per ray: {coarse + fine}"
    )
    flops = nerf_mlp_flops_per_ray(model)
    note = ""
    if isinstance(model, RefNeRF):
        note = "; excludes the density-gradient backward pass for the normals (about 2x the spatial MLP)"
    lines.append(
        f"MLP FLOPs per ray (forward, 2 x MACs): {flops['total']:,} "
        f"(coarse {flops['coarse']:,} + fine {flops['fine']:,}){note}"
    )
    lines.append(f"GFLOPs per 800x800 frame (NeRF-synthetic size): {flops['total'] * 800 * 800 / 1e9:,.1f}")
    return "\n".join(lines)
