"""What `stage=summary` and the benchmark report of a radiance field: parameters, samples per ray, MLP
FLOPs per ray, and the training step's activation memory (estimated from the architecture).

Activation memory of a training step = rays x sum over levels (samples of the level x bytes per sample),
with bytes per sample = element size x floats saved for the backward pass per sample. The MLPs never
form their concatenations (`fields.SkipMLP`), so each tensor is kept once: a SkipMLP keeps its per-sample
input and every layer's output (the next layer's input, or the heads' shared one):

    floats = sum_m (per-sample in_dim(m) + width(m) x depth(m))   over the trunk and the view MLP m
           + width x depth + 4 (pos_dim + view_dim)                Ref-NeRF only (view_dim: the IDE's)

NeRF's view encoding is one row per ray (not counted). Ref-NeRF differentiates its density w.r.t. the
sample positions with `create_graph=True` (its normals, Verbin et al. 2022 Sec. 3), which keeps about
one more trunk-sized set of tensors for the double backward, and its IPE and IDE (Eq. 7-8) keep a few
encoding-sized tensors. Calibrated on CPU against the bytes of the tensors autograd saves
(`saved_tensors_hooks`), the formula is within 1 % at paper size, 6 % at the cpu profile and 45 % at the
tiny smoke sizes, where the encodings and volume rendering (not counted) dominate
(tests/test_nerf_fidelity.py measures it). That is about 10.0 KB per sample for NeRF and mip-NeRF and
28.5 KB for Ref-NeRF, so Ref-NeRF's paper step (16384 rays x 256 samples) needs about 119 GB;
`task.train.micro_batch_rays` divides it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from torch import nn

from src.models.instantiate import model_dict
from src.models.nerf.fields import NerfMLP, RefNerfMLP, SkipMLP
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


def _skip_mlp_floats(mlp: SkipMLP, per_sample_in: int) -> int:
    return per_sample_in + mlp.width * mlp.depth


def activation_floats_per_sample(mlp: nn.Module) -> int:
    """Floats one sample keeps for the backward pass through `mlp` (the module docstring's formula)."""
    if isinstance(mlp, NerfMLP):  # the view encoding is kept once per ray, not per sample
        view = mlp.view_mlp
        return _skip_mlp_floats(mlp.trunk, mlp.trunk.in_dim) + _skip_mlp_floats(
            view, view.in_dim - mlp.view_dim
        )
    if isinstance(mlp, RefNerfMLP):  # the density gradient's graph (double backward) and the encodings
        trunk, view = mlp.trunk, mlp.view_mlp
        floats = _skip_mlp_floats(trunk, trunk.in_dim) + _skip_mlp_floats(view, view.in_dim)
        return floats + trunk.width * trunk.depth + 4 * (trunk.in_dim + mlp.view_encoding.out_dim)
    return sum(m.in_features for m in mlp.modules() if isinstance(m, nn.Linear))


def activation_bytes_per_ray(model: NerfModelBase) -> int:
    """Estimated bytes of saved activations per training ray: sum over levels of samples x bytes/sample."""
    size = next(model.parameters()).element_size()
    samples = model.samples_per_level()
    return sum(s * size * activation_floats_per_sample(model.mlp_for(i)) for i, s in enumerate(samples))


def activation_bytes(model: NerfModelBase, rays: int) -> int:
    """Estimated activation memory (bytes) of a forward + backward pass on `rays` training rays."""
    return rays * activation_bytes_per_ray(model)


def fitting_micro_batch(model: NerfModelBase, free_bytes: float, fraction: float = 0.8) -> int:
    """The largest power-of-two ray count whose estimated activations use at most `fraction` of
    `free_bytes` (the rest: parameters, optimiser state, the backward's transient buffers); 0 if none."""
    rays = int(fraction * free_bytes) // activation_bytes_per_ray(model)
    return 0 if rays < 1 else 1 << (rays.bit_length() - 1)


def activation_line(model: NerfModelBase, batch_size: int, micro_batch_rays: int | None) -> str:
    """The `stage=summary` line of a training step's estimated activation memory."""
    rays = batch_size if micro_batch_rays is None else min(int(micro_batch_rays), batch_size)
    samples = sum(model.samples_per_level())
    per_sample = activation_bytes_per_ray(model) / samples
    how = "the whole batch" if rays == batch_size else f"micro-batches of {rays} of {batch_size} rays"
    return (
        f"activation memory per training step (estimate, {how}): "
        f"{activation_bytes(model, rays) / 1e9:,.2f} GB = {rays} rays x {samples} samples x "
        f"{per_sample / 1e3:,.1f} KB per sample"
    )


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
