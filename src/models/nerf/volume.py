"""Volume rendering of per-interval densities and colours (NeRF, Mildenhall et al. 2020, Eq. 3)."""

from __future__ import annotations

import torch
from torch import Tensor

#: NeRF's "infinite" last interval (Mildenhall et al. 2020, released code: `dists` padded with 1e10).
OPAQUE_DELTA = 1e10


def compute_alpha_weights(
    density: Tensor, tdist: Tensor, dirs: Tensor, opaque_last: bool = False
) -> tuple[Tensor, Tensor, Tensor]:
    """Quadrature weights of NeRF Eq. 3.

    delta_i = (t_{i+1} - t_i) ||d|| (metric interval length), alpha_i = 1 - exp(-sigma_i delta_i),
    T_i = exp(-sum_{j<i} sigma_j delta_j) (exclusive cumulative sum), w_i = T_i alpha_i.
    With `opaque_last` the last delta is 1e10 instead (NeRF's released code, whose last sample's
    distance "to infinity" is 1e10): any density in the last interval makes alpha = 1 there, so the
    weights sum to 1 and the background shows only through rays empty up to the far bound. mip-NeRF and
    multinerf use the real last interval (the default).

    Args:
        density: (N, S) non-negative sigma per interval; tdist: (N, S+1); dirs: (N, 3) ray directions.

    Returns:
        (weights, alpha, trans), each (N, S).
    """
    delta = (tdist[..., 1:] - tdist[..., :-1]) * torch.linalg.vector_norm(dirs, dim=-1, keepdim=True)
    if opaque_last:
        delta = torch.cat([delta[..., :-1], torch.full_like(delta[..., -1:], OPAQUE_DELTA)], dim=-1)
    density_delta = density * delta
    alpha = 1.0 - torch.exp(-density_delta)
    excl = torch.cat([torch.zeros_like(density_delta[..., :1]), density_delta[..., :-1]], dim=-1)
    trans = torch.exp(-torch.cumsum(excl, dim=-1))
    return alpha * trans, alpha, trans


def volumetric_rendering(
    rgb: Tensor, weights: Tensor, tdist: Tensor, background: Tensor
) -> dict[str, Tensor]:
    """Composite per-interval colours on a background (NeRF Eq. 3, its released white-background form).

    rgb_ray = sum_i w_i c_i + (1 - acc) * background with acc = sum_i w_i; depth = the expected interval
    midpoint sum_i w_i t_i / acc, clipped to [t_0, t_S] (an empty ray reads t_0). With directions of
    camera-space z = -1, the ray parameter t is the camera z-depth.

    Args:
        rgb: (N, S, 3); weights: (N, S); tdist: (N, S+1); background: (3,) or (N, 3).

    Returns:
        {"rgb": (N, 3), "depth": (N,), "acc": (N,)}.
    """
    acc = weights.sum(dim=-1)
    bg_w = torch.clamp(1.0 - acc[..., None], min=0.0)
    rgb_out = (weights[..., None] * rgb).sum(dim=-2) + bg_w * background
    t_mids = 0.5 * (tdist[..., 1:] + tdist[..., :-1])
    eps = torch.finfo(weights.dtype).eps
    depth = (weights * t_mids).sum(dim=-1) / torch.clamp(acc, min=eps)
    depth = torch.minimum(torch.maximum(depth, tdist[..., 0]), tdist[..., -1])
    return {"rgb": rgb_out, "depth": depth, "acc": acc}
