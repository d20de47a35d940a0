"""The floored flicker (`flicker_unbiased`) and Noisebase's temporal PSNR (`temporal_psnr`) of
src/metrics/temporal.py, by value against closed forms of synthetic sequences: a smooth true sequence and
independent Gaussian noise of known standard deviation in each reference; and both in the sequence
evaluation (src/eval/denoise_eval.py), the floored one only where an item has a second reference."""

import math

import numpy as np
import pytest

from src.errors import DataError
from src.metrics.temporal import flicker_unbiased, temporal_error, temporal_psnr
from tests.conftest import one_line_error
from tests.sequence_eval_stub import stub_frames, stub_sequence_eval
from tests.test_volume_shards import SPPS

F, H, W, C = 8, 48, 48, 3
M = (F - 1) * H * W * C  # frame differences per sequence
SLOPE = 0.03  # the truth brightens by this much per frame, everywhere
SIGMA1, SIGMA2 = 0.02, 0.03  # the two references' noise: unequal on purpose (e.g. different spp)


def _truth_and_refs(seed=0):
    """A smooth true sequence in [0.3, 0.76] (so the `clip` tone map is the identity on it and on its noisy
    renders: the noise stays > 8 sigma inside [0, 1]) and two references of independent noise."""
    rng = np.random.default_rng(seed)
    truth = rng.uniform(0.3, 0.55, (1, H, W, C)) + SLOPE * np.arange(F).reshape(F, 1, 1, 1)
    r1 = truth + rng.normal(0.0, SIGMA1, truth.shape)
    r2 = truth + rng.normal(0.0, SIGMA2, truth.shape)
    return rng, truth, r1, r2


def _squared(value):
    """The estimate F^2 back from the signed root the metric reports."""
    return np.sign(value) * value**2


# Sampling tolerance of F^2 for the truth: F^2 = mean(Δn1 Δn2) there (expand the squares), a mean of M
# products of standard deviation sqrt(2) s1 sqrt(2) s2, neighbouring ones correlated (a frame is in two
# differences): 5 standard errors with that correlation's factor sqrt(1.5).
TRUTH_TOL = 5 * 2 * SIGMA1 * SIGMA2 * np.sqrt(1.5 / M)


def test_the_truth_scores_zero_within_the_sampling_tolerance():
    _, truth, r1, r2 = _truth_and_refs()
    assert abs(_squared(flicker_unbiased(truth, r1, r2, "clip"))) < TRUTH_TOL
    assert TRUTH_TOL < 0.05 * 2 * SIGMA1**2  # far below what the noisy sequences below score


def test_the_old_flicker_floor_is_the_references_noise_2_sigma_over_sqrt_pi():
    # What the issue measured: the truth scores E|Δn1| = 2 s1 / sqrt(pi) under temporal_error, not 0.
    _, truth, r1, _ = _truth_and_refs()
    assert temporal_error(truth, r1, "clip") == pytest.approx(2 * SIGMA1 / np.sqrt(np.pi), rel=0.02)


def test_per_frame_noise_scores_sqrt2_sigma_and_a_reference_quality_render_as_much():
    rng, truth, r1, r2 = _truth_and_refs(seed=1)
    sigma_o = 0.025
    noisy = truth + rng.normal(0.0, sigma_o, truth.shape)
    # E[(Δo - Δt)^2] = Var(Δn_o) = 2 s_o^2, so the RMS is sqrt(2) s_o.
    assert _squared(flicker_unbiased(noisy, r1, r2, "clip")) == pytest.approx(2 * sigma_o**2, rel=0.03)
    # An independent third render at the first reference's noise: sqrt(2) s1, not 0 as it would "match".
    third = truth + rng.normal(0.0, SIGMA1, truth.shape)
    assert flicker_unbiased(third, r1, r2, "clip") == pytest.approx(np.sqrt(2) * SIGMA1, rel=0.02)


def test_a_copy_of_either_reference_scores_exactly_zero_so_copying_noise_cannot_beat_the_truth():
    _, _, r1, r2 = _truth_and_refs(seed=2)
    assert flicker_unbiased(r1, r1, r2, "clip") == pytest.approx(0.0, abs=1e-7)
    assert flicker_unbiased(r2, r1, r2, "clip") == pytest.approx(0.0, abs=1e-7)


def test_a_frozen_first_frame_scores_the_truths_motion():
    # Δo = 0, so e = -Δt = -SLOPE everywhere: F^2 = SLOPE^2 + mean(Δn1 Δn2) + SLOPE (mean Δn1 + mean Δn2),
    # the last terms within the truth's tolerance (the means of Δn_i telescope to (n_last - n_first) / 7).
    _, truth, r1, r2 = _truth_and_refs(seed=3)
    frozen = np.repeat(truth[:1], F, axis=0)
    assert _squared(flicker_unbiased(frozen, r1, r2, "clip")) == pytest.approx(SLOPE**2, abs=TRUTH_TOL)
    assert TRUTH_TOL < 0.05 * SLOPE**2
    # The old metric mixes the motion with the reference's noise: E|X| for X ~ N(mu, s^2), mu = SLOPE,
    # s = sqrt(2) SIGMA1, is s sqrt(2 / pi) exp(-mu^2 / (2 s^2)) + mu erf(mu / (s sqrt(2))).
    mu, s = SLOPE, np.sqrt(2) * SIGMA1
    folded = s * np.sqrt(2 / np.pi) * np.exp(-(mu**2) / (2 * s**2)) + mu * math.erf(mu / (s * np.sqrt(2)))
    assert temporal_error(frozen, r1, "clip") == pytest.approx(folded, rel=0.02)


def test_a_negative_estimate_is_reported_as_a_negative_root_not_clipped():
    # References with opposite noise (n2 = -n1, not independent: a constructed case) make F^2 for the
    # truth exactly mean(Δn1 Δn2) = -mean(Δn1^2).
    rng, truth, _, _ = _truth_and_refs(seed=4)
    noise = rng.normal(0.0, SIGMA1, truth.shape)
    expected = -np.sqrt(np.mean(np.diff(noise, axis=0) ** 2))
    assert flicker_unbiased(truth, truth + noise, truth - noise, "clip") == pytest.approx(expected, rel=1e-9)


def _np_flicker_unbiased(frames, r1, r2, gamma=2.2):
    """The estimator as a per-pair loop over the clip_gamma tone-mapped frames."""
    tm = lambda x: np.clip(x, 0.0, 1.0) ** (1.0 / gamma)  # noqa: E731
    a, b, c = [], [], []
    for t in range(frames.shape[0] - 1):
        d_o, d_1, d_2 = (tm(x[t + 1]) - tm(x[t]) for x in (frames, r1, r2))
        a.append(((d_o - d_1) ** 2).mean())
        b.append(((d_o - d_2) ** 2).mean())
        c.append(((d_1 - d_2) ** 2).mean())
    estimate = (np.mean(a) + np.mean(b)) / 2 - np.mean(c) / 2
    return np.sign(estimate) * np.sqrt(abs(estimate))


def test_hdr_sequences_are_tone_mapped_on_every_side_by_default():
    # HDR values below 0 and above 1: the default clip_gamma 2.2 changes every sequence differently.
    rng = np.random.default_rng(5)
    r1 = rng.uniform(-0.2, 1.5, (4, 3, 5, 3))
    r2 = r1 + rng.normal(0.0, 0.2, r1.shape)
    output = r1 + rng.normal(0.0, 0.3, r1.shape)
    expected = _np_flicker_unbiased(output, r1, r2)
    assert flicker_unbiased(output, r1, r2) == pytest.approx(expected, rel=1e-12)
    assert abs(expected) > 0.05


def test_flicker_unbiased_rejects_a_second_reference_of_another_shape():
    _, truth, r1, r2 = _truth_and_refs()
    with pytest.raises(DataError) as excinfo:
        flicker_unbiased(truth, r1, r2[:-1])
    one_line_error(excinfo, "reference2", str(r2[:-1].shape))


# -- temporal PSNR (Noisebase) --


def _offset_sequence(offsets, seed=6):
    """A moving reference in [0.2, 0.7] and the output = reference + a constant per frame."""
    rng = np.random.default_rng(seed)
    reference = rng.uniform(0.2, 0.7, (len(offsets), 6, 7, 3))
    return reference + np.reshape(offsets, (-1, 1, 1, 1)), reference


def test_temporal_psnr_is_the_mean_over_pairs_of_the_psnr_of_the_differences():
    # Offsets 0, a, 3a, 2a: Δo - Δr is a, 2a, -a on every pixel; pair PSNRs -20 log10(a), -20 log10(2a),
    # -20 log10(a) with peak 1; their mean (37.993 dB for a = 0.01), not the dB of the mean MSE (36.99).
    a = 0.01
    output, reference = _offset_sequence([0.0, a, 3 * a, 2 * a])
    expected = -20 * np.log10(a) - 20 * np.log10(2) / 3
    assert temporal_psnr(output, reference, "clip") == pytest.approx(expected, rel=1e-9)
    # warmup 1 drops the first pair: mean(-20 log10(2a), -20 log10(a)).
    expected_warm = -20 * np.log10(a) - 20 * np.log10(2) / 2
    assert temporal_psnr(output, reference, "clip", warmup=1) == pytest.approx(expected_warm, rel=1e-9)


def test_temporal_psnr_tone_maps_both_sides():
    # gamma 2 on values in [0, 1]: the PSNR of the differences of the square roots.
    output, reference = _offset_sequence([0.0, 0.02, 0.05])
    d = np.diff(np.sqrt(output), axis=0) - np.diff(np.sqrt(reference), axis=0)
    expected = np.mean([10 * np.log10(1 / np.mean(d[t] ** 2)) for t in range(2)])
    assert temporal_psnr(output, reference, "clip_gamma", gamma=2.0) == pytest.approx(expected, rel=1e-12)


def test_temporal_psnr_is_infinite_for_identical_changes_and_quantises_as_noisebase_on_request():
    _, reference = _offset_sequence([0.0] * 4)
    assert temporal_psnr(reference, reference) == np.inf
    # Reference on the 8-bit grid (plus 0.1 level); offsets of 0.001 < 1/255 vanish in 8 bits only.
    levels = np.random.default_rng(7).integers(50, 200, (4, 6, 7, 3))
    reference = (levels + 0.1) / 255
    output = reference + np.reshape([0.0, 0.001, 0.0, 0.001], (-1, 1, 1, 1))
    assert temporal_psnr(output, reference, "clip") == pytest.approx(-20 * np.log10(0.001), rel=1e-6)
    assert temporal_psnr(output, reference, "clip", quantize=True) == np.inf


def test_temporal_psnr_rejects_a_warmup_that_leaves_no_pair():
    output, reference = _offset_sequence([0.0, 0.1, 0.2])
    with pytest.raises(DataError) as excinfo:
        temporal_psnr(output, reference, warmup=2)
    one_line_error(excinfo, "warmup 2", "3 frames")


# -- in the sequence evaluation --


TONEMAP = ["metrics.tonemap=reinhard_gamma", "metrics.gamma=2.2"]


def _evaluate(vol_data, tmp_path, monkeypatch, second: bool, undefined_spp: int | None = None):
    """(summary, logged metrics, per_image rows) of the stubbed evaluation (tests/sequence_eval_stub.py)."""
    run = stub_sequence_eval(vol_data, tmp_path, monkeypatch, TONEMAP, undefined_spp, second_reference=second)
    return run.summary, run.logged, run.rows


def test_sequence_evaluation_reports_temporal_psnr_and_no_floored_flicker_without_a_second_reference(
    vol_data, tmp_path, monkeypatch
):
    summary, logged, rows = _evaluate(vol_data, tmp_path, monkeypatch, second=False)
    assert len(rows) == 2
    for row in rows.itertuples():
        denoised, noisy, reference, _ = stub_frames(row)
        tm = ("reinhard_gamma", 2.2)
        assert row.tpsnr == pytest.approx(temporal_psnr(denoised, reference, *tm), rel=1e-5)
        assert row.noisy_tpsnr == pytest.approx(temporal_psnr(noisy, reference, *tm), rel=1e-5)
        assert row.temporal == pytest.approx(temporal_error(denoised, reference, *tm), rel=1e-5)
        assert logged[f"eval_tpsnr_spp{row.spp}"] == pytest.approx(row.tpsnr, rel=1e-12)
    assert abs(rows["tpsnr"] - rows["noisy_tpsnr"]).min() > 1.0  # the fixture tells output and input apart
    assert logged["eval_tpsnr"] == pytest.approx(rows["tpsnr"].mean(), rel=1e-12)
    assert "flicker_unbiased" not in rows and not any(
        "flicker_unbiased" in k for k in (*summary["mean"], *logged)
    )


def test_sequence_evaluation_reports_the_floored_flicker_where_items_have_a_second_reference(
    vol_data, tmp_path, monkeypatch
):
    summary, logged, rows = _evaluate(vol_data, tmp_path, monkeypatch, second=True)
    assert len(rows) == 2
    for row in rows.itertuples():
        denoised, noisy, reference, reference2 = stub_frames(row)
        tm = ("reinhard_gamma", 2.2)
        expected = flicker_unbiased(denoised, reference, reference2, *tm)
        expected_noisy = flicker_unbiased(noisy, reference, reference2, *tm)
        assert row.flicker_unbiased == pytest.approx(expected, rel=1e-5)
        assert row.noisy_flicker_unbiased == pytest.approx(expected_noisy, rel=1e-5)
        assert abs(expected - expected_noisy) > 0.01 and abs(expected) > 0.01
        assert logged[f"eval_flicker_unbiased_spp{row.spp}"] == pytest.approx(row.flicker_unbiased, rel=1e-12)
        assert logged[f"eval_noisy_flicker_unbiased_spp{row.spp}"] == pytest.approx(
            row.noisy_flicker_unbiased, rel=1e-12
        )
    assert summary["mean"]["flicker_unbiased"] == pytest.approx(rows["flicker_unbiased"].mean(), rel=1e-12)
    assert logged["eval_flicker_unbiased"] == pytest.approx(rows["flicker_unbiased"].mean(), rel=1e-12)


def test_an_item_with_an_undefined_frame_scores_nan_and_is_counted_not_fatal(vol_data, tmp_path, monkeypatch):
    summary, logged, rows = _evaluate(vol_data, tmp_path, monkeypatch, second=True, undefined_spp=min(SPPS))
    bad, good = rows[rows.spp == min(SPPS)].iloc[0], rows[rows.spp != min(SPPS)].iloc[0]
    assert bad.undefined == pytest.approx(0.25) and good.undefined == 0.0  # one of its four frames
    for key in (
        "psnr",
        "ssim",
        "relmse",
        "relmse_spp",
        "relmse_ratio",
        "temporal",
        "tpsnr",
        "flicker_unbiased",
    ):
        assert np.isnan(bad[key]) and not np.isnan(good[key]), key  # psnr: inf (frame 0 is exact)
        assert summary["mean"][key] == pytest.approx(good[key], rel=1e-12), key  # the defined item's value
    for key in ("noisy_psnr", "noisy_relmse_spp", "noisy_temporal", "noisy_flicker_unbiased"):
        assert np.isfinite(bad[key]), key  # the input is still scored
    _, noisy, reference, _ = stub_frames(bad)
    assert bad.noisy_tpsnr == pytest.approx(temporal_psnr(noisy, reference, "reinhard_gamma", 2.2), rel=1e-5)
    assert logged["eval_undefined"] == pytest.approx(0.125)
    assert logged[f"eval_undefined_spp{min(SPPS)}"] == pytest.approx(0.25)
    assert np.isnan(logged[f"eval_psnr_spp{min(SPPS)}"])
