"""Per-pixel kernel application for kernel-predicting denoisers (KPCN, residual KPCN).

Bako et al. 2017 ("Kernel-Predicting Convolutional Networks for Denoising Monte Carlo Renderings"),
Eq. (5)-(6): the network predicts k*k scores z_p for every pixel p; they are normalised with a softmax,

    w_pq = exp(z_pq) / sum_q' exp(z_pq'),

and the denoised value is the weighted average of the noisy (transformed) colour over the k x k window,

    c_hat_p = sum_{q in N(p)} w_pq * c_q.

The weights are positive and sum to one, so the output stays inside the convex hull of the window and
a constant image is preserved exactly.

Why not `F.unfold`: unfolding a 1280x720 frame with a 21x21 window holds 441 copies of the image (~4.9 GB);
a Python loop over pixels took 140 s per frame in the seed thesis. Here the sum is accumulated over the
kernel taps instead, O(k*k*C*H*W) flops and never more than O(N*C*H*W + N*k*k*H*W) memory (the size of
the logits), in one of two orders:

- "offset" (default for CPU inference): one tap at a time: exp of one H x W plane of scores, then one
  fused multiply-add over the frame. Everything stays cache-sized; 4 small ops per tap.
- "row" (default on CUDA and whenever autograd records): one kernel row (k taps) at a time, through a
  strided `unfold` view of k image columns (no copy) and one (N, C, H, W, k) product. ~20x fewer kernel
  launches than "offset" (k*k*4 launches would dominate a small training patch), at k times the image in
  temporary memory. Under autograd "offset" also records k*k*4 graph nodes, each replayed backward: a
  cpu-profile KPCN training step (16 patches of 32 x 32, k = 11, 2 threads) took 700 ms with it against
  375 ms with "row" and 350 ms for the networks alone.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

#: FLOPs of the softmax per kernel tap (subtract the max, exp, add to the normaliser).
SOFTMAX_FLOPS_PER_TAP = 3


def kernel_application_flops(kernel_size: int, channels: int = 3) -> int:
    """FLOPs per pixel of one kernel application: 2 * k*k*channels (weighted sum, Bako et al. 2017, Eq. 5-6)
    + the softmax over the k*k taps."""
    taps = kernel_size * kernel_size
    return 2 * taps * channels + SOFTMAX_FLOPS_PER_TAP * taps


def _check_shapes(logits: torch.Tensor, image: torch.Tensor, kernel_size: int) -> None:
    if kernel_size < 1 or kernel_size % 2 == 0:
        raise ValueError(f"kernel_size must be a positive odd integer, got {kernel_size}")
    if logits.ndim != 4 or image.ndim != 4:
        raise ValueError(
            f"expected (N, C, H, W) tensors, got logits {tuple(logits.shape)}, image {tuple(image.shape)}"
        )
    kk = kernel_size * kernel_size
    n, c, h, w = logits.shape
    if c != kk or (n, h, w) != (image.shape[0], *image.shape[2:]):
        raise ValueError(
            f"logits {tuple(logits.shape)} must be (N, {kk}, H, W) for image {tuple(image.shape)} "
            f"with a {kernel_size}x{kernel_size} kernel"
        )


def _accumulate_by_offset(logits, padded, peak, kernel_size, height, width):
    """(numerator, normaliser), one tap at a time."""
    k = kernel_size
    numerator = padded.new_zeros((*padded.shape[:2], height, width))
    normaliser = torch.zeros_like(peak)
    for i in range(k):
        rows = padded[:, :, i : i + height]
        for j in range(k):
            idx = i * k + j
            # exp of one cache-resident plane per tap: ~3x faster on CPU than one (k*k, H, W) exp up front.
            weight = (logits[:, idx : idx + 1] - peak).exp_()
            numerator.addcmul_(rows[:, :, :, j : j + width], weight)
            normaliser.add_(weight)
    return numerator, normaliser


def _accumulate_by_row(logits, padded, peak, kernel_size, height, width):
    """(numerator, normaliser), one kernel row of k taps at a time."""
    k = kernel_size
    numerator = padded.new_zeros((*padded.shape[:2], height, width))
    normaliser = torch.zeros_like(peak)
    for i in range(k):
        weight = (logits[:, i * k : (i + 1) * k] - peak).exp()  # (N, k, H, W): taps (i, 0..k-1)
        normaliser.add_(weight.sum(dim=1, keepdim=True))
        # window[n, c, y, x, j] = padded[n, c, y + i, x + j]: a strided view, not a copy.
        window = padded[:, :, i : i + height].unfold(3, k, 1)
        numerator.add_((window * weight.permute(0, 2, 3, 1).unsqueeze(1)).sum(dim=-1))
    return numerator, normaliser


ACCUMULATORS = {"offset": _accumulate_by_offset, "row": _accumulate_by_row}


def default_order(logits: torch.Tensor, image: torch.Tensor) -> str:
    """The accumulation order: "row" on CUDA or when autograd records the call, else "offset"."""
    recording = torch.is_grad_enabled() and (logits.requires_grad or image.requires_grad)
    return "row" if image.device.type == "cuda" or recording else "offset"


def apply_kernel(
    logits: torch.Tensor, image: torch.Tensor, kernel_size: int, order: str | None = None
) -> torch.Tensor:
    """Softmax-normalise per-pixel kernel scores and filter `image` with them (Bako et al. 2017, Eq. 5-6).

    Args:
        logits: (N, k*k, H, W) raw scores; channel i*k + j is the weight of the pixel at row offset
            dy = i - k//2 and column offset dx = j - k//2.
        image: (N, C, H, W) image to filter (the same kernel is used for every channel).
        kernel_size: k, odd.
        order: "offset" or "row" accumulation (see the module docstring); None picks "row" on CUDA or
            when autograd records (training), "offset" otherwise. Both give the same result up to the
            order of the float sums.

    Returns:
        (N, C, H, W) with out[n, c, y, x] = sum_{i,j} w[n, i*k+j, y, x] * image[n, c, y+i-k//2, x+j-k//2],
        where image borders are extended by *replicate* padding (a softmax kernel then preserves a constant
        image at the borders too). Computed in float32 at least (bf16/fp16 autocast inputs are upcast: a
        441-term sum in half precision loses ~3 significant bits); differentiable.
    """
    _check_shapes(logits, image, kernel_size)
    order = order or default_order(logits, image)
    if order not in ACCUMULATORS:
        raise ValueError(f"order must be one of {sorted(ACCUMULATORS)}, got {order!r}")
    dtype = torch.promote_types(torch.promote_types(logits.dtype, image.dtype), torch.float32)
    logits, image = logits.to(dtype), image.to(dtype)
    r = kernel_size // 2
    # Stable softmax: subtracting the per-pixel max keeps exp() <= 1. The max cancels in the ratio, so it
    # is detached (its gradient is exactly zero).
    peak = logits.amax(dim=1, keepdim=True).detach()
    padded = F.pad(image, (r, r, r, r), mode="replicate") if r > 0 else image
    numerator, normaliser = ACCUMULATORS[order](logits, padded, peak, kernel_size, *image.shape[-2:])
    # The largest tap contributes exp(0) = 1, so the normaliser is >= 1: no division by zero.
    return numerator / normaliser
