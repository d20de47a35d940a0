"""Per-pixel sample statistics (src/render/moments.py) by value: the variance of a pixel mean from the
film's mean and raw second moment, on hand-sized samples, with channels of different spread, moving
means, cancellation and passes of unequal sizes (the mutation group `moments` runs against this file)."""

import numpy as np
import pytest

from src.render.moments import MomentAccumulator, variance_of_mean
from tests.conftest import one_line_error


def test_variance_of_the_mean_of_two_and_four_samples_by_hand():
    """Samples (1, 3): mean 2, second moment 5, sample variance ((1-2)^2 + (3-2)^2) / 1 = 2, its mean's
    variance 2 / 2 = 1; a constant channel adds 0 and the channels are averaged (one value per buffer)."""
    mean, second = np.array([[2.0, 7.0]]), np.array([[5.0, 49.0]])
    out = variance_of_mean(mean, second, 2)
    assert out.shape == (1, 1) and out[0, 0] == pytest.approx(0.5)
    # Four samples -1, 0, 2, 7 (mean 2, second 13.5): sample variance (9 + 4 + 0 + 25) / 3, mean's / 4.
    samples = np.array([-1.0, 0.0, 2.0, 7.0])
    out = variance_of_mean(np.array([[samples.mean()]]), np.array([[np.mean(samples**2)]]), 4)
    assert out[0, 0] == pytest.approx(38 / 3 / 4)


def test_variance_of_the_mean_per_pixel_averages_channels_not_pixels():
    """Pixels with different means and spreads: each pixel its own value, the mean over its channels
    (brute force with numpy's ddof=1 variance), shape (H, W, 1)."""
    rng = np.random.default_rng(3)
    n = 5
    samples = rng.normal(
        loc=[[[-4.0, 0.5, 10.0]], [[3.0, -2.0, 0.0]]], scale=[0.1, 1.0, 5.0], size=(n, 2, 1, 3)
    )
    mean, second = samples.mean(0), np.square(samples).mean(0)
    expected = samples.var(axis=0, ddof=1).mean(-1, keepdims=True) / n
    out = variance_of_mean(mean, second, n)
    assert out.shape == (2, 1, 1)
    np.testing.assert_allclose(out, expected, rtol=1e-10)
    assert out[0, 0, 0] != pytest.approx(out[1, 0, 0], rel=0.1)


def test_cancellation_is_clamped_to_zero_not_negative():
    """A constant pixel of large value whose second moment rounds below mean^2: variance 0, not < 0; a
    pixel with real spread beside it keeps its value."""
    mean = np.array([[[1e4, 1e4]], [[1.0, 1.0]]], dtype=np.float32)
    second = np.array([[[1e8 * (1 - 1e-7), 1e8]], [[3.0, 3.0]]], dtype=np.float32)
    out = variance_of_mean(mean, second, 8)
    assert out[0, 0, 0] == 0.0
    assert out[1, 0, 0] == pytest.approx((3.0 - 1.0) / 7)


@pytest.mark.parametrize("n", [0, 1])
def test_fewer_than_two_samples_is_an_error(n):
    with pytest.raises(ValueError, match=f"at least 2 samples per pixel, got {n}"):
        variance_of_mean(np.zeros((1, 1, 3)), np.zeros((1, 1, 3)), n)
    assert variance_of_mean(np.zeros((1, 1, 3)), np.ones((1, 1, 3)), 2)[0, 0, 0] == 1.0


def test_the_accumulator_weights_passes_by_their_sample_counts_in_float64():
    """Passes of 1, 3 and 12 samples with different means: the merged mean is the sample-weighted one
    (not the mean of the pass means), accumulated in float64 from float32 passes, and n is the total."""
    passes = [
        (np.full((2, 2, 3), 4.0, np.float32), 1),
        (np.full((2, 2, 3), -2.0, np.float32), 3),
        (np.array([[[1.0, 2.0, 3.0]] * 2, [[0.5, 0.25, 1e-3]] * 2], np.float32), 12),
    ]
    acc = MomentAccumulator()
    for means, spp in passes:
        acc.add(means, spp)
    expected = sum(m.astype(np.float64) * s for m, s in passes) / 16
    assert acc.n == 16 and acc.mean().dtype == np.float64
    np.testing.assert_allclose(acc.mean(), expected, rtol=1e-15)
    assert acc.mean()[0, 0, 0] == pytest.approx((4 - 6 + 12) / 16)


def test_the_accumulator_keeps_float64_precision_across_passes():
    """float32 pass means 1 + k 2^-20 (exact in float32) merged over 64 passes of one sample: the exact
    mean 1 + 31.5 * 2^-20, which a float32 running sum misses (its steps near 64 are 2^-17)."""
    acc = MomentAccumulator()
    for k in range(64):
        acc.add(np.array([[[1 + k * 2.0**-20]]], np.float32), 1)
    assert acc.mean()[0, 0, 0] == 1 + 31.5 * 2.0**-20


def test_the_accumulator_without_a_pass_is_an_error():
    with pytest.raises(ValueError, match="no pass added"):
        MomentAccumulator().mean()


def test_variance_of_mean_matches_brute_force():
    rng = np.random.default_rng(0)
    samples = rng.gamma(2.0, 1.5, size=(64, 5, 7, 3))  # n samples of a (5, 7, 3) image
    n = samples.shape[0]
    mean, second = samples.mean(0), np.square(samples).mean(0)
    expected = (samples.var(0, ddof=1) / n).mean(-1, keepdims=True)
    np.testing.assert_allclose(variance_of_mean(mean, second, n), expected, rtol=1e-10)
    with pytest.raises(ValueError) as excinfo:
        variance_of_mean(mean, second, 1)
    one_line_error(excinfo, "at least 2 samples per pixel, got 1")


def test_moment_accumulator_merges_passes_of_different_sizes():
    rng = np.random.default_rng(1)
    samples = rng.normal(size=(10, 3, 4, 2))
    acc = MomentAccumulator()
    acc.add(samples[:7].mean(0), 7)
    acc.add(samples[7:].mean(0), 3)
    np.testing.assert_allclose(acc.mean(), samples.mean(0), rtol=1e-12)


# Surviving mutants of src/render/moments.py (bash scripts/mutation.sh moments), all equivalent here:
# - MomentAccumulator.add `pass_means.astype(np.float64)` -> `astype(None)`: numpy reads dtype None as
#   float64, so the passes are still accumulated in float64.
