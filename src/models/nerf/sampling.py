"""Where to sample along rays: stratified intervals and inverse-CDF resampling (pure functions).

All three models use one representation: a ray is cut into S intervals by S + 1 sorted endpoints
`tdist` (N, S+1) in units of the ray parameter t (x = o + t d). mip-NeRF casts a cone through each
interval; NeRF evaluates its MLP at the interval midpoints, with delta_i = t_{i+1} - t_i (Mildenhall et al.
2020, Eq. 3). One volume renderer (`volume.py`) then serves every model.
"""

from __future__ import annotations

import torch
from torch import Tensor


def stratified_samples(
    near: Tensor,
    far: Tensor,
    n_samples: int,
    randomized: bool,
    lindisp: bool = False,
    generator: torch.Generator | None = None,
    jitter: Tensor | None = None,
) -> Tensor:
    """S = n_samples intervals between near and far, jittered when `randomized` (NeRF Eq. 2).

    The S + 1 evenly spaced endpoints (in t, or in 1/t when `lindisp`) are each moved uniformly within
    [previous midpoint, next midpoint] (the first within [near, first midpoint], the last within
    [last midpoint, far]), as in mip-NeRF's released code: the intervals stay sorted and disjoint and,
    in expectation, tile [near, far].

    Args:
        near, far: (N, 1) ray bounds.
        generator: RNG for the jitter (on the tensors' device); None uses the global one.
        jitter: (N, n_samples + 1) uniform draws to use instead of drawing them (drawn for a whole batch
            up front, so that splitting the batch into micro-batches samples the same intervals).

    Returns:
        tdist (N, n_samples + 1), sorted along the last axis.
    """
    t = torch.linspace(0.0, 1.0, n_samples + 1, dtype=near.dtype, device=near.device)
    tdist = 1.0 / (1.0 / near * (1.0 - t) + 1.0 / far * t) if lindisp else near * (1.0 - t) + far * t
    if randomized:
        mids = 0.5 * (tdist[..., 1:] + tdist[..., :-1])
        upper = torch.cat([mids, tdist[..., -1:]], dim=-1)
        lower = torch.cat([tdist[..., :1], mids], dim=-1)
        u = jitter
        if u is None:
            u = torch.rand(tdist.shape, generator=generator, dtype=tdist.dtype, device=tdist.device)
        tdist = lower + (upper - lower) * u.to(tdist.dtype)
    return tdist


def sample_pdf(
    bins: Tensor,
    weights: Tensor,
    n_samples: int,
    randomized: bool,
    generator: torch.Generator | None = None,
    eps: float = 1e-5,
    jitter: Tensor | None = None,
) -> Tensor:
    """Inverse-transform samples of the piecewise-constant pdf `weights` on `bins` (NeRF Sec. 5.2).

    Bin i is [bins[i], bins[i+1]] with probability weights[i] / sum(weights), uniform inside. A ray
    whose weights sum below `eps` is padded towards uniform (no NaN on empty rays). The quantiles u are
    stratified (one uniform draw per 1/n_samples stratum, mip-NeRF) when `randomized`, else evenly spaced
    in [0, 1 - eps]; either way they are sorted, so the samples come out sorted.

    Args:
        bins: (N, B+1) sorted bin edges; weights: (N, B) non-negative.
        jitter: (N, n_samples) uniform draws to use instead of drawing them (`randomized` only).

    Returns:
        (N, n_samples) samples.
    """
    weight_sum = weights.sum(dim=-1, keepdim=True)
    padding = torch.clamp(eps - weight_sum, min=0.0)
    weights = weights + padding / weights.shape[-1]
    weight_sum = weight_sum + padding
    pdf = weights / weight_sum
    cdf = torch.clamp(torch.cumsum(pdf[..., :-1], dim=-1), max=1.0)
    zeros = torch.zeros_like(cdf[..., :1])
    cdf = torch.cat([zeros, cdf, torch.ones_like(zeros)], dim=-1)  # (N, B+1), like bins

    shape = (*cdf.shape[:-1], n_samples)
    if randomized:
        if jitter is None:
            jitter = torch.rand(shape, generator=generator, dtype=cdf.dtype, device=cdf.device)
        jitter = jitter.to(cdf.dtype)
        strata = torch.arange(n_samples, dtype=cdf.dtype, device=cdf.device)
        u = torch.clamp((strata + jitter) / n_samples, max=1.0 - eps)
    else:
        u = torch.linspace(0.0, 1.0 - eps, n_samples, dtype=cdf.dtype, device=cdf.device).expand(shape)
    u = u.contiguous()

    # cdf[below] <= u < cdf[above]: with repeated cdf values (empty bins) `below` is the last of them, so
    # the chosen bin is the one with mass.
    above = torch.searchsorted(cdf.contiguous(), u, right=True).clamp(max=cdf.shape[-1] - 1)
    below = (above - 1).clamp(min=0)
    cdf_0, cdf_1 = cdf.gather(-1, below), cdf.gather(-1, above)
    bins_0, bins_1 = bins.gather(-1, below), bins.gather(-1, above)
    denom = cdf_1 - cdf_0
    frac = torch.where(denom > 0, (u - cdf_0) / torch.where(denom > 0, denom, 1.0), 0.0).clamp(0.0, 1.0)
    return bins_0 + frac * (bins_1 - bins_0)


def blur_weights(weights: Tensor, padding: float) -> Tensor:
    """mip-NeRF's resampling histogram (Barron et al. 2021, Sec. 3.2): a 2-tap max filter then a 2-tap box
    filter (the 'blurpool' of each weight with its neighbours, edges replicated), plus `padding`."""
    w_pad = torch.cat([weights[..., :1], weights, weights[..., -1:]], dim=-1)
    w_max = torch.maximum(w_pad[..., :-1], w_pad[..., 1:])
    return 0.5 * (w_max[..., :-1] + w_max[..., 1:]) + padding


def resample_draws(n_samples: int, blur_padding: float | None) -> int:
    """Uniform draws per ray `resample_tdist` makes: n_samples + 1 new endpoints (mip-NeRF) or n_samples
    importance samples (NeRF)."""
    return n_samples + 1 if blur_padding is not None else n_samples


def resample_tdist(
    tdist: Tensor,
    weights: Tensor,
    n_samples: int,
    randomized: bool,
    blur_padding: float | None = None,
    generator: torch.Generator | None = None,
    jitter: Tensor | None = None,
) -> Tensor:
    """The fine level's intervals from the coarse level's weights (gradients stopped); `jitter`: the
    (N, `resample_draws(n_samples, blur_padding)`) uniform draws to use instead of drawing them.

    - mip-NeRF (`blur_padding` a float, 0.01 in the paper): n_samples + 1 new endpoints drawn from the
      blurred, padded weights (`blur_weights`), replacing the coarse ones: (N, n_samples + 1).
    - NeRF (`blur_padding` None): n_samples importance samples from the weights, merged with the coarse
      endpoints and sorted (NeRF Sec. 5.2: the fine network sees N_c + N_f points): (N, S + 1 + n_samples).
    """
    tdist, weights = tdist.detach(), weights.detach()
    if blur_padding is not None:
        blurred = blur_weights(weights, blur_padding)
        return sample_pdf(tdist, blurred, n_samples + 1, randomized, generator, jitter=jitter)
    fine = sample_pdf(tdist, weights, n_samples, randomized, generator, jitter=jitter)
    return torch.sort(torch.cat([tdist, fine], dim=-1), dim=-1).values
