"""The samples a denoiser saves: the sample count a plain render would need to reach a denoised image's
error, read from the noisy renders' own error against sample count.

The Monte Carlo law. A render at n samples per pixel is an unbiased estimate X_n of the pixel's integral
with variance sigma^2 / n; the reference R is an independent estimate at N_ref samples. The expected
squared error of X_n against R is therefore

    E[(X_n - R)^2] = sigma^2 / n + sigma^2 / N_ref  =  a / n + c,                    (1)

averaged over the pixels: `a` is the image's per-sample variance and `c` the reference's own noise, the
floor no render can go below when measured against this reference. `fit_monte_carlo` fits (1) to an
image's ladder of noisy counts (non-negative least squares on relative errors, so that every rung counts
alike) and reports how well the law holds there (the RMS of log(measured / fitted)).

A denoised image D of measured error e_D = E[(D - R)^2] has its own error e_D - c (its error and the
reference's noise are independent), which a plain render reaches at

    n* = a / (e_D - c).                                                              (2)

What can be measured is bounded: the ladder's largest count (beyond it (1) would be extrapolated) and the
reference's noise (when e_D - c is below `margin` x c, the difference is mostly the reference's noise; with
margin 1 that bound, a / c, is the reference's own sample count N_ref). Past a bound `spp_equivalent`
says "at least" the bound, never an extrapolated number.

The speed-up of a denoiser is the render time it saves: a plain render at n* against the input render plus
the denoising, `speedup`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import nnls

from src.errors import DataError


@dataclass(frozen=True)
class MonteCarloFit:
    """Eq. (1) fitted to one image's ladder: error = variance / spp + floor."""

    variance: float  # a: the per-sample variance, in the error's units
    floor: float  # c: what the reference's own noise adds to every measured error
    residual: float  # RMS of log(measured / fitted) over the ladder (0: the law holds exactly)
    max_spp: float  # the ladder's largest count: no equivalent is read beyond it

    def error_at(self, spp: float) -> float:
        return self.variance / spp + self.floor


@dataclass(frozen=True)
class SppEquivalent:
    value: float  # samples per pixel; a lower bound when `at_least`
    at_least: bool  # the denoised error lies past what the ladder and the reference can measure


def fit_monte_carlo(spp: Sequence[float], errors: Sequence[float]) -> MonteCarloFit:
    """Fit Eq. (1) to mean squared errors `errors` of renders at sample counts `spp` (at least two
    distinct counts, positive errors): non-negative least squares on relative errors (each row divided by
    its measured error), as scipy's `nnls` solves it. One rung's error is one draw of a heavy-tailed
    quantity (a firefly can raise a single render's error several times); `residual` shows such a rung (a
    robust soft-L1 refit was tried on the smoke ladder and moved the fit by under 5%: not worth its code)."""
    n, e = np.asarray(spp, dtype=np.float64), np.asarray(errors, dtype=np.float64)
    if n.shape != e.shape or n.ndim != 1 or len(np.unique(n)) < 2:
        raise DataError(
            f"spp ladder {list(spp)}: expected at least two distinct sample counts, one error each"
        )
    if not (np.all(n > 0) and np.all(np.isfinite(e)) and np.all(e > 0)):
        raise DataError(
            f"spp ladder errors {list(errors)}: expected positive, finite errors at positive counts"
        )
    design = np.stack([1.0 / n, np.ones_like(n)], axis=1) / e[:, None]
    (a, c), _ = nnls(design, np.ones_like(e))
    fitted = a / n + c
    residual = float(np.sqrt(np.mean(np.log(e / fitted) ** 2))) if np.all(fitted > 0) else math.inf
    return MonteCarloFit(float(a), float(c), residual, float(n.max()))


def measurable_limit(fit: MonteCarloFit, margin: float = 1.0) -> float:
    """The largest sample count an equivalent can be read at: the ladder's top, or a / (margin x c), where
    the denoised image's own error is `margin` times the reference's noise (Eq. (2) at
    e_D = (1 + margin) c)."""
    if margin <= 0:
        raise ValueError(f"margin={margin}: expected a positive ratio")
    by_reference = math.inf if fit.floor == 0 else fit.variance / (margin * fit.floor)
    return min(fit.max_spp, by_reference)


def spp_equivalent(fit: MonteCarloFit, error: float, margin: float = 1.0) -> SppEquivalent:
    """Eq. (2) for a denoised image of measured error `error` (same metric and reference as the fit), or
    "at least" `measurable_limit` when it lies past it."""
    limit = measurable_limit(fit, margin)
    own = error - fit.floor
    if own <= 0 or fit.variance / own > limit:
        return SppEquivalent(limit, True)
    return SppEquivalent(fit.variance / own, False)


def seconds_per_spp(spp: Sequence[float], seconds: Sequence[float]) -> float:
    """The render seconds one more sample per pixel costs: the slope of seconds = t0 + k x spp fitted to the
    ladder's timed rungs (non-negative least squares: a fixed cost per render, such as compiling the
    kernels, goes to t0 and not to k). Falls back to the largest rung's seconds / spp when the slope comes
    out 0 (timings too noisy to tell). NaN when a rung has no time (NaN: a ladder averaged from stored
    samples, such as a Noisebase set's, was never rendered here), so no speed-up is claimed."""
    n, t = np.asarray(spp, dtype=np.float64), np.asarray(seconds, dtype=np.float64)
    if n.shape != t.shape or n.ndim != 1 or len(np.unique(n)) < 2 or not np.all(n > 0):
        raise DataError(f"render timings at spp {list(spp)}: expected at least two distinct positive counts")
    if np.isnan(t).any():
        return math.nan
    (_, slope), _ = nnls(np.stack([np.ones_like(n), n], axis=1), t)
    if slope > 0:
        return float(slope)
    top = int(np.argmax(n))
    return float(t[top] / n[top])


def speedup(equivalent_spp: float, input_spp: float, render_s_per_spp: float, denoise_s: float) -> float:
    """How many times faster the denoiser reaches its quality than a plain render: the render at the
    equivalent count against the input render plus the denoising (seconds per spp measured by the render
    stage, for the same image)."""
    return equivalent_spp * render_s_per_spp / (input_spp * render_s_per_spp + denoise_s)


def geometric_mean(values: Sequence[float]) -> float:
    """The geometric mean of sample counts or speed-ups (ratios: a 2x above and a 2x below cancel), NaN
    values left out (an undefined output has no equivalent); NaN when none is left."""
    finite = np.asarray(values, dtype=np.float64)
    finite = finite[~np.isnan(finite)]
    return float(np.exp(np.mean(np.log(finite)))) if finite.size else math.nan
