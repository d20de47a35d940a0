"""Temporal stability of a denoised sequence: how much it flickers relative to the reference.

Per-frame metrics (PSNR, SSIM, relMSE) cannot see flicker: a denoiser whose residual noise changes from
frame to frame scores the same as one whose residual is steady, yet only the first shimmers in motion.
The metric here compares the frame-to-frame changes of the output with those of the reference,

    temporal_error = mean_{t, p, c} | (o_{t+1} - o_t)(p, c) - (r_{t+1} - r_t)(p, c) |,

on the tone-mapped frames (the display values PSNR/SSIM see, `metrics.tonemap`), so it is in display
units, comparable across scenes, and zero for an output that changes exactly as the reference does (a
copy of it; not the noise-free truth: see its floor below). It is the signed temporal-derivative term of
the training loss (`src.objectives.temporal.temporal_loss`, after Chaitanya et al. 2017 and the 2023
production volumetric denoising talk) used as a metric, unwarped: camera and media motion are in the
reference's differences too, so they cancel wherever the output follows the reference.

Its floor. A Monte Carlo reference is the truth plus noise, r = t + n, and its own frame-to-frame change
Δr = Δt + Δn is partly noise: a perfect output (Δo = Δt) scores mean |Δn|, not 0 (for Gaussian noise of
standard deviation s per frame, independent between frames, E|Δn| = 2 s / sqrt(pi)), and an output that
copies the reference's noise would score better than the truth. `flicker_unbiased` removes that floor
with a second, independent reference; `temporal_psnr` is the Noisebase benchmark's temporal PSNR.

`flicker_unbiased`: two references r1 = t + n1, r2 = t + n2 of the same frames rendered with different
seeds, so n1, n2 are independent of each other and of the output o (a denoiser never sees them), with
zero mean (in display units: t is the expected tone-mapped reference, E tonemap(r), per frame). Then,
with squared differences and e = Δo - Δt (the output's flicker against the truth),

    E[(Δo - Δr_i)^2] = E[e^2] - 2 E[e Δn_i] + E[Δn_i^2] = E[e^2] + V_i,    V_i = Var(Δn_i),
    E[(Δr1 - Δr2)^2] = E[(Δn1 - Δn2)^2] = V_1 + V_2,

so    F^2 = (mean((Δo - Δr1)^2) + mean((Δo - Δr2)^2)) / 2 - mean((Δr1 - Δr2)^2) / 2

is an unbiased estimate of E[e^2], the mean squared flicker against the noise-free truth. Both references
in the first term (not r1 alone) make it unbiased even when V_1 != V_2 (references of different sample
counts), halve the noise of the estimate, and score a copy of either reference exactly 0 (F^2 = 0 for
o = r1: copying a reference's noise ties with the truth, it cannot beat it). The truth scores 0 in
expectation, a frozen first frame mean(Δt^2), per-frame noise of standard deviation s_o 2 s_o^2. The
metric is the signed root sign(F^2) sqrt(|F^2|), an RMS in display units: an estimate below zero (an
output within the estimate's own sampling noise of the truth) is reported negative, never clipped to 0,
so that a mean over items is not pushed up by the clipping. The alternative, a reference of many more
samples for the held-out sequences only, lowers the floor without removing it and costs far more render
time than a second reference at the same count.

`temporal_psnr`: PSNR of the frame differences (Balint et al. 2023, "Neural Partitioning Pyramids for
Denoising Monte Carlo Renderings", the Noisebase benchmark; `noisebase/scripts/nb_compute_metrics.py`,
`TemporalMetricAdapter(psnr)`): per consecutive pair, 10 log10(1 / mean((Δo - Δr)^2)) over pixels and
channels, on display values in [0, 1] with peak 1 (although differences span [-1, 1]), then the mean of
those dB values over the pairs (not the dB of the mean MSE). Where ours differs or the source is silent:
Noisebase tone-maps with ACES (`noisebase/data.py::ACES`, gamma 2.2) and stores 8-bit PNGs (truncated,
`astype(np.uint8)`) before scoring; we tone-map with `metrics.tonemap` (the values PSNR/SSIM see) and
quantise only on request (`quantize=True`), so our values are not comparable with published Noisebase
numbers. Noisebase skips the first `warmup` frames (16 in its test sets) of a sequence (`warmup` here,
0 by default: our sequences are short and their denoisers not recurrent). A pair whose differences agree
exactly gives +inf (Noisebase divides by zero there); the mean is then +inf. It keeps the reference's
noise in Δr, so its ceiling for the truth is finite (the floor above, in dB).
"""

from __future__ import annotations

import numpy as np

from src.errors import DataError
from src.metrics.image import tonemap


def temporal_error(
    frames: np.ndarray, reference: np.ndarray, method: str = "clip_gamma", gamma: float = 2.2
) -> float:
    """mean |Δt tonemap(frames) - Δt tonemap(reference)| over consecutive frames, pixels and channels
    (module docstring); `frames` and `reference` are (F, H, W, C) linear HDR with F >= 2."""
    out, ref = _tonemapped_pair(frames, reference, method, gamma, "temporal metric")
    return float(np.abs(np.diff(out, axis=0) - np.diff(ref, axis=0)).mean())


def _tonemapped_pair(frames, reference, method, gamma, what: str):
    """Both sequences checked ((F >= 2, H, W, C), one shape) and tone-mapped."""
    frames, reference = np.asarray(frames), np.asarray(reference)
    if frames.shape != reference.shape or frames.ndim != 4 or frames.shape[0] < 2:
        raise DataError(
            f"{what}: expected two (F >= 2, H, W, C) sequences of one shape, got {frames.shape} "
            f"and {reference.shape}"
        )
    return tonemap(frames, method, gamma), tonemap(reference, method, gamma)


def flicker_unbiased(
    frames: np.ndarray,
    reference: np.ndarray,
    reference2: np.ndarray,
    method: str = "clip_gamma",
    gamma: float = 2.2,
) -> float:
    """sign(F^2) sqrt(|F^2|) with F^2 = (mean((Δo - Δr1)^2) + mean((Δo - Δr2)^2)) / 2
    - mean((Δr1 - Δr2)^2) / 2 over consecutive frames, pixels and channels of the tone-mapped sequences:
    the RMS flicker against the noise-free truth, estimated without bias from two independent references
    (module docstring: the algebra, and why a negative estimate is reported negative). All three are
    (F, H, W, C) linear HDR with F >= 2."""
    out, ref = _tonemapped_pair(frames, reference, method, gamma, "flicker metric")
    _, ref2 = _tonemapped_pair(frames, reference2, method, gamma, "flicker metric (reference2)")
    d_out, d_ref, d_ref2 = np.diff(out, axis=0), np.diff(ref, axis=0), np.diff(ref2, axis=0)
    against_refs = (np.mean((d_out - d_ref) ** 2) + np.mean((d_out - d_ref2) ** 2)) / 2
    noise = np.mean((d_ref - d_ref2) ** 2) / 2
    estimate = float(against_refs - noise)
    return float(np.sign(estimate) * np.sqrt(abs(estimate)))


def temporal_psnr(
    frames: np.ndarray,
    reference: np.ndarray,
    method: str = "clip_gamma",
    gamma: float = 2.2,
    warmup: int = 0,
    quantize: bool = False,
) -> float:
    """Noisebase's temporal PSNR (module docstring): mean over consecutive pairs t of frames
    warmup..F-1 of 10 log10(1 / mean_{p, c}((Δo_t - Δr_t)^2)), on the tone-mapped frames (floored to
    8 bits, as Noisebase's PNGs, when `quantize`); +inf where a pair's differences agree exactly."""
    out, ref = _tonemapped_pair(frames, reference, method, gamma, "temporal PSNR")
    if not 0 <= warmup <= out.shape[0] - 2:
        raise DataError(f"temporal PSNR: warmup {warmup} leaves fewer than 2 of {out.shape[0]} frames")
    out, ref = out[warmup:], ref[warmup:]
    if quantize:  # Noisebase: (ACES(x) * 255).astype(np.uint8) / 255
        out, ref = np.floor(out * 255) / 255, np.floor(ref * 255) / 255
    mse = np.mean((np.diff(out, axis=0) - np.diff(ref, axis=0)) ** 2, axis=(1, 2, 3))
    with np.errstate(divide="ignore"):
        return float(np.mean(10 * np.log10(1.0 / mse)))
