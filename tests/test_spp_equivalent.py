"""The spp-equivalent (src/metrics/spp_equivalent.py): the Monte Carlo law fitted to renders of known
variance, the equivalent of a denoised image of known error, and the bound the ladder and the reference's
own noise put on what can be measured."""

from __future__ import annotations

import math

import numpy as np
import pytest

from src.errors import DataError
from src.metrics.spp_equivalent import (
    MonteCarloFit,
    SppEquivalent,
    fit_monte_carlo,
    geometric_mean,
    measurable_limit,
    speedup,
    spp_equivalent,
)

SIGMA = 0.5  # per-sample standard deviation of the synthetic integrand
REFERENCE_SPP = 4096
PIXELS = 256 * 256


def _image(rng, mean, spp):
    """A render at `spp` samples of an integrand of per-sample variance SIGMA^2: mean + N(0, SIGMA^2/spp)."""
    return mean + rng.normal(0.0, SIGMA / np.sqrt(spp), size=mean.shape)


def _ladder(top=1024, seed=0):
    rng = np.random.default_rng(seed)
    mean = rng.uniform(0.0, 1.0, size=PIXELS)
    reference = _image(rng, mean, REFERENCE_SPP)
    counts = [2**k for k in range(int(np.log2(top)) + 1)]
    errors = [float(np.mean((_image(rng, mean, n) - reference) ** 2)) for n in counts]
    return rng, mean, reference, counts, errors


def test_an_exact_law_is_fitted_exactly():
    counts = [1, 4, 16, 64]
    fit = fit_monte_carlo(counts, [2.0 / n + 0.01 for n in counts])
    assert fit.variance == pytest.approx(2.0, rel=1e-9) and fit.floor == pytest.approx(0.01, rel=1e-9)
    assert fit.residual == pytest.approx(0.0, abs=1e-9) and fit.max_spp == 64
    assert fit.error_at(8) == pytest.approx(2.0 / 8 + 0.01)


def test_renders_of_known_variance_give_the_variance_and_the_references_noise():
    _, _, _, counts, errors = _ladder()
    fit = fit_monte_carlo(counts, errors)
    assert fit.variance == pytest.approx(SIGMA**2, rel=0.02)
    assert fit.floor == pytest.approx(SIGMA**2 / REFERENCE_SPP, rel=0.1)
    assert fit.residual < 0.02


@pytest.mark.parametrize("m", [3, 40, 300])
def test_a_denoised_image_as_good_as_m_samples_reads_m(m):
    rng, mean, reference, counts, errors = _ladder()
    fit = fit_monte_carlo(counts, errors)
    denoised = _image(rng, mean, m)  # what a denoiser worth m samples would give
    equivalent = spp_equivalent(fit, float(np.mean((denoised - reference) ** 2)))
    assert not equivalent.at_least and equivalent.value == pytest.approx(m, rel=0.1)


def test_past_the_ladder_or_the_references_noise_it_is_at_least_the_bound():
    rng, mean, reference, counts, errors = _ladder(top=1024)
    fit = fit_monte_carlo(counts, errors)
    beyond_ladder = spp_equivalent(fit, float(np.mean((_image(rng, mean, 3000) - reference) ** 2)))
    assert beyond_ladder == SppEquivalent(1024.0, True)  # the ladder's top, not an extrapolated 3000
    perfect = spp_equivalent(fit, float(np.mean((mean - reference) ** 2)))  # the true image: only noise left
    assert perfect.at_least and perfect.value == 1024.0
    # A ladder past the reference's own count: the reference's noise is the bound (a / c = N_ref at margin 1).
    _, _, _, counts, errors = _ladder(top=16384, seed=1)
    fit = fit_monte_carlo(counts, errors)
    assert measurable_limit(fit) == pytest.approx(REFERENCE_SPP, rel=0.15)
    assert measurable_limit(fit, margin=2.0) == pytest.approx(measurable_limit(fit) / 2, rel=1e-9)
    assert spp_equivalent(fit, fit.floor * 0.9).at_least  # below the floor: noise, not a measurement
    assert spp_equivalent(fit, fit.floor) == SppEquivalent(measurable_limit(fit), True)  # at it


def test_the_bound_is_one_sided_at_its_edge():
    fit = MonteCarloFit(variance=1.0, floor=0.001, residual=0.0, max_spp=10_000)
    limit = measurable_limit(fit)  # a / c = 1000
    assert limit == pytest.approx(1000.0)
    inside = spp_equivalent(fit, 0.001 + 1.0 / 999)
    assert not inside.at_least and inside.value == pytest.approx(999.0)
    outside = spp_equivalent(fit, 0.001 + 1.0 / 1001)
    assert outside == SppEquivalent(limit, True)


def test_speedup_is_the_render_time_saved():
    # 512 spp-equivalent from 4 spp at 0.01 s per spp plus 0.5 s of denoising: 5.12 s / 0.54 s
    assert speedup(512, 4, 0.01, 0.5) == pytest.approx(5.12 / 0.54)
    assert speedup(4, 4, 0.01, 0.0) == pytest.approx(1.0)


def test_the_summary_is_the_geometric_mean_with_undefined_values_left_out():
    # the range and the share of lower bounds are the table's: tests/test_ladder.py (samples saved)
    assert geometric_mean([10.0, 1000.0]) == pytest.approx(100.0)
    assert geometric_mean([10.0, float("nan"), 1000.0]) == pytest.approx(100.0)
    assert math.isnan(geometric_mean([])) and math.isnan(geometric_mean([float("nan")]))


@pytest.mark.parametrize(
    ("spp", "errors", "needle"),
    [([4, 4], [0.1, 0.1], "two distinct"), ([4], [0.1], "two distinct"), ([1, 4], [0.1, 0.0], "positive")],
)
def test_a_ladder_that_cannot_be_fitted_is_one_line(spp, errors, needle):
    with pytest.raises(DataError, match=needle) as err:
        fit_monte_carlo(spp, errors)
    assert "\n" not in str(err.value)
