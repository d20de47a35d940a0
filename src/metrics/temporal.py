"""Temporal stability of a denoised sequence: how much it flickers relative to the reference.

Per-frame metrics (PSNR, SSIM, relMSE) cannot see flicker: a denoiser whose residual noise changes from
frame to frame scores the same as one whose residual is steady, yet only the first shimmers in motion.
The metric here compares the frame-to-frame changes of the output with those of the reference,

    temporal_error = mean_{t, p, c} | (o_{t+1} - o_t)(p, c) - (r_{t+1} - r_t)(p, c) |,

on the tone-mapped frames (the display values PSNR/SSIM see, `metrics.tonemap`), so it is in display
units, comparable across scenes, and zero for an output that changes exactly as the reference does
(including a perfect one). It is the signed temporal-derivative term of the training loss
(`src.train.temporal.temporal_loss`, after Chaitanya et al. 2017 and the 2023 production volumetric
denoising talk) used as a metric, unwarped: camera and media motion are in the reference's differences
too, so they cancel wherever the output follows the reference.
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
    frames, reference = np.asarray(frames), np.asarray(reference)
    if frames.shape != reference.shape or frames.ndim != 4 or frames.shape[0] < 2:
        raise DataError(
            f"temporal metric: expected two (F >= 2, H, W, C) sequences of one shape, got {frames.shape} "
            f"and {reference.shape}"
        )
    out, ref = tonemap(frames, method, gamma), tonemap(reference, method, gamma)
    return float(np.abs(np.diff(out, axis=0) - np.diff(ref, axis=0)).mean())
