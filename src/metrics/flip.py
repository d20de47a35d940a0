"""FLIP (Andersson et al. 2020, "FLIP: A Difference Evaluator for Alternating Images"; HDR-FLIP, Andersson
et al. 2021) through NVIDIA's `flip_evaluator` package.

Conventions:
- `flip(test, reference, mode)` returns the mean of the per-pixel FLIP error map, in [0, 1]; 0 for
  identical images. Images are (H, W, 3) float arrays, `reference` is the ground truth.
- mode "hdr": HDR-FLIP on linear (scene-referred) linear-sRGB colour; negative values are clipped to 0
  (FLIP requires nonnegative HDR input). FLIP chooses its exposure range and uses its default ACES tone
  mapper, independent of `metrics.tonemap`.
- mode "ldr": LDR-FLIP on display-referred (sRGB-encoded, here the tone-mapped) values in [0, 1]; values
  are clipped to [0, 1].
- Default viewing conditions: 67 pixels per degree (0.7 m from a 0.7 m wide 3840-pixel monitor).
"""

from __future__ import annotations

import numpy as np

from src.errors import ConfigError, DataError

FLIP_MODES = ("hdr", "ldr")


def flip(test: np.ndarray, reference: np.ndarray, mode: str = "hdr") -> float:
    """Mean FLIP error of `test` against `reference` (both (H, W, 3)); see the module docstring."""
    import flip_evaluator  # imported lazily: a compiled extension only the metric needs

    if mode not in FLIP_MODES:
        raise ConfigError(f"metrics.flip.mode={mode!r}; expected one of {', '.join(FLIP_MODES)}")
    t, r = np.asarray(test, dtype=np.float32), np.asarray(reference, dtype=np.float32)
    if t.shape != r.shape or t.ndim != 3 or t.shape[-1] != 3:
        raise DataError(f"flip: expected two (H, W, 3) images, got {t.shape} and {r.shape}")
    if mode == "hdr":
        t, r = np.maximum(t, 0.0), np.maximum(r, 0.0)
    else:
        t, r = np.clip(t, 0.0, 1.0), np.clip(r, 0.0, 1.0)
    _, mean, _ = flip_evaluator.evaluate(
        np.ascontiguousarray(r), np.ascontiguousarray(t), mode.upper(), applyMagma=False
    )
    return float(mean)
