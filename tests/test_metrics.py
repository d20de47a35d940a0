"""Image metrics (src/metrics/image.py) against closed forms and an independent SSIM implementation."""

import warnings
from pathlib import Path

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view

from src.errors import ConfigError, DataError
from src.metrics.flip import flip
from src.metrics.image import (
    energy,
    image_metrics,
    lpips_model,
    lpips_variant,
    mse,
    psnr,
    relmse,
    relmse_spp,
    smape,
    ssim,
    tonemap,
)
from src.metrics.lpips import lpips_distance
from tests.conftest import compose_config, one_line_error


def reference_ssim(x, y, win_size=11, sigma=1.5, k1=0.01, k2=0.03, data_range=1.0):
    """Straightforward SSIM (Wang et al. 2004): normalised Gaussian window, population statistics, only
    windows fully inside the image ("valid"), mean over positions and channels (dm_pix convention)."""
    r = win_size // 2
    offsets = np.arange(-r, r + 1)
    g = np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma**2))
    g /= g.sum()
    c1, c2 = (k1 * data_range) ** 2, (k2 * data_range) ** 2

    def local_mean(a):  # (H, W, C) -> (H - 2r, W - 2r, C)
        windows = sliding_window_view(a, (win_size, win_size), axis=(0, 1))  # (h, w, C, k, k)
        return np.einsum("hwckl,kl->hwc", windows, g)

    mx, my = local_mean(x), local_mean(y)
    vx = local_mean(x * x) - mx**2
    vy = local_mean(y * y) - my**2
    cxy = local_mean(x * y) - mx * my
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return s.mean()


def test_psnr_of_a_known_mse():
    y = np.full((8, 10, 3), 0.5)
    x = y + 0.1  # MSE = 0.01
    assert psnr(x, y) == pytest.approx(10 * np.log10(1 / 0.01))
    assert psnr(x, y) == pytest.approx(20.0)
    assert psnr(y, y) == float("inf")
    assert mse(x, y) == pytest.approx(0.01)


def test_ssim_of_identical_images_is_one():
    x = np.random.default_rng(0).uniform(0, 1, (16, 20, 3))
    assert ssim(x, x) == pytest.approx(1.0)


def test_ssim_matches_an_independent_implementation():
    rng = np.random.default_rng(1)
    x = rng.uniform(0, 1, (23, 31, 3))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    expected = reference_ssim(x, y)
    assert 0.3 < expected < 0.99  # a pair that is neither identical nor unrelated
    assert ssim(x, y) == pytest.approx(expected, rel=1e-9, abs=1e-12)


def test_ssim_window_must_match_the_gaussian_footprint():
    x = np.zeros((16, 16, 3))
    with pytest.raises(ConfigError) as excinfo:
        ssim(x, x, win_size=7, sigma=1.5)
    one_line_error(excinfo, "metrics.ssim.win_size=7", "11")
    with pytest.raises(DataError) as excinfo:
        ssim(np.zeros((8, 16, 3)), np.zeros((8, 16, 3)))
    one_line_error(excinfo, "8x16")


def test_relmse_and_smape_by_hand():
    x = np.array([[[1.0, 0.0, 2.0]]])
    y = np.array([[[0.5, 0.0, 1.0]]])
    eps = 0.01
    # per channel: 0.25 / 0.26, 0 / 0.01, 1 / 1.01; averaged over all 3 channels
    assert relmse(x, y, eps) == pytest.approx((0.25 / 0.26 + 0.0 + 1.0 / 1.01) / 3)
    # per channel: 0.5 / 1.51, 0 / 0.01, 1 / 3.01
    assert smape(x, y, eps) == pytest.approx((0.5 / 1.51 + 0.0 + 1.0 / 3.01) / 3)


def test_smape_of_negative_values_by_hand():
    # Linear HDR can be negative (a denoiser's undershoot): the denominator is |x| + |y| + eps, never
    # x + y + eps (which would give 2 / 0.01 for the first channel).
    x = np.array([[[-1.0, -2.0, 3.0]]])
    y = np.array([[[1.0, -0.5, -1.0]]])
    assert smape(x, y, 0.01) == pytest.approx((2.0 / 2.01 + 1.5 / 2.51 + 4.0 / 4.01) / 3)
    assert smape(y, x, 0.5) == pytest.approx((2.0 / 2.5 + 1.5 / 3.0 + 4.0 / 4.5) / 3)


def test_relmse_of_the_gp_thesis_sums_channels_and_scales_by_half_the_spp():
    """Davletaliyev 2016, Eq. 3.5: (1/N) sum_i (m/2) sum_rgb (x - y)^2 / (y^2 + eps): two pixels by hand,
    1.5 m times Bako et al.'s mean-over-channels relMSE, and the factor cancels in the fitness ratio."""
    x = np.array([[[1.0, 0.0, 2.0], [0.5, 0.5, 0.5]]])
    y = np.array([[[0.5, 0.0, 1.0], [0.5, 0.5, 0.0]]])
    per_pixel = [0.25 / 0.26 + 0.0 + 1.0 / 1.01, 0.25 / 0.01]
    assert relmse_spp(x, y, spp=8, eps=0.01) == pytest.approx(8 / 2 * sum(per_pixel) / 2)
    assert relmse_spp(x, y, spp=8) == pytest.approx(1.5 * 8 * relmse(x, y, 0.01))
    noisy = x + 0.3
    ratio = relmse_spp(x, y, 16) / relmse_spp(noisy, y, 16)
    assert ratio == pytest.approx(relmse(x, y) / relmse(noisy, y))
    with pytest.raises(ValueError, match="spp must be >= 1"):
        relmse_spp(x, y, spp=0)


def test_relmse_border_crop_ignores_the_border():
    reference = np.ones((10, 12, 3))
    x = reference.copy()
    x[:2] = x[-2:] = x[:, :2] = x[:, -2:] = 5.0  # a 2-pixel frame of filter border artefacts
    assert relmse(x, reference, 1e-4) > 1.0
    assert relmse(x, reference, 1e-4, crop=2) == 0.0
    x[5, 6, 0] = 2.0  # inside the crop: counted, over the 6 x 8 x 3 values left
    assert relmse(x, reference, 1e-4, crop=2) == pytest.approx(1.0 / (1.0 + 1e-4) / (6 * 8 * 3))
    with pytest.raises(ConfigError) as excinfo:
        relmse(x, reference, crop=5)
    one_line_error(excinfo, "metrics.relmse_crop", "12x10")


def test_tonemap_values():
    x = np.array([-1.0, 0.0, 0.25, 1.0, 4.0])
    np.testing.assert_allclose(tonemap(x, "clip_gamma", 2.0), [0, 0, 0.5, 1, 1])
    np.testing.assert_allclose(tonemap(x, "reinhard_gamma", 1.0), [0, 0, 0.2, 0.5, 0.8])
    np.testing.assert_allclose(tonemap(np.array([3.0]), "reinhard_gamma", 2.0), [np.sqrt(0.75)])
    np.testing.assert_allclose(tonemap(x, "clip", 2.2), [0, 0, 0.25, 1, 1])  # sRGB input: no gamma
    with pytest.raises(ConfigError) as excinfo:
        tonemap(x, "aces")
    one_line_error(excinfo, "metrics.tonemap", "aces")


def test_shape_mismatch_and_nonfinite_are_one_line_data_errors():
    cfg = compose_config().metrics
    with pytest.raises(DataError) as excinfo:
        image_metrics(np.zeros((16, 20, 3)), np.zeros((20, 16, 3)), cfg)
    one_line_error(excinfo, "(16, 20, 3)", "(20, 16, 3)")
    bad = np.zeros((16, 20, 3))
    bad[3, 4, 1] = np.nan
    with pytest.raises(DataError) as excinfo:
        image_metrics(bad, np.zeros((16, 20, 3)), cfg)
    one_line_error(excinfo, "NaN/Inf", "denoised")


def test_image_metrics_from_the_real_config():
    cfg = compose_config().metrics
    rng = np.random.default_rng(2)
    reference = rng.uniform(0, 3, (24, 32, 3))  # HDR: clip_gamma clips values above 1
    denoised = reference * 1.05
    m = image_metrics(denoised, reference, cfg)
    assert set(m) == {"psnr", "ssim", "relmse", "smape", "mse", "energy", "energy_error", "lpips", "flip"}
    assert m["energy"] == pytest.approx(1.05) and m["energy_error"] == pytest.approx(0.05)
    darker = image_metrics(reference * 0.9, reference, cfg)
    assert darker["energy"] == pytest.approx(0.9) and darker["energy_error"] == pytest.approx(0.1)
    x_ldr, y_ldr = tonemap(denoised, cfg.tonemap, cfg.gamma), tonemap(reference, cfg.tonemap, cfg.gamma)
    assert m["psnr"] == pytest.approx(10 * np.log10(1 / np.mean((x_ldr - y_ldr) ** 2)))
    assert m["ssim"] == pytest.approx(reference_ssim(x_ldr, y_ldr))
    assert m["relmse"] == pytest.approx(np.mean((0.05 * reference) ** 2 / (reference**2 + cfg.relmse_eps)))
    assert m["mse"] == pytest.approx(np.mean((0.05 * reference) ** 2))
    same = image_metrics(reference, reference, cfg)
    assert same["psnr"] == float("inf") and same["ssim"] == pytest.approx(1.0)
    assert same["relmse"] == same["smape"] == same["mse"] == 0.0
    assert same["energy"] == 1.0 and same["energy_error"] == 0.0


def test_energy_by_value():
    """mean(output) / mean(reference) over pixels and channels: a scaled reference gives the scale, the
    truth 1.0; unequal images by hand (a per-pixel or per-channel mean of ratios would differ)."""
    rng = np.random.default_rng(5)
    reference = rng.uniform(0.1, 4.0, (12, 10, 3))
    assert energy(reference, reference) == 1.0
    assert energy(0.895 * reference, reference) == pytest.approx(0.895)
    y = np.array([[[1.0, 1.0, 1.0], [3.0, 3.0, 3.0]]])  # mean 2
    x = np.array([[[2.0, 0.0, 1.0], [0.0, 0.0, 0.0]]])  # mean 0.5; mean of per-pixel ratios: 1/2
    assert energy(x, y) == pytest.approx(0.25)
    assert energy(-x, y) == pytest.approx(-0.25)  # a negative output mean is reported as it is
    assert np.isnan(energy(x, -y)) and np.isnan(energy(x, np.zeros_like(y)))  # no meaningful ratio
    assert energy(x, 1e-9 * y) == pytest.approx(0.25e9)  # a dim but positive reference still has one
    with pytest.raises(DataError):
        energy(x, y[:, :1])


# --- mutation-testing additions (scripts/mutation.sh): every setting must reach the number it changes ---


def small_pair(seed=3, shape=(16, 20, 3)):
    rng = np.random.default_rng(seed)
    reference = rng.uniform(0, 2, shape)
    return np.clip(reference + rng.normal(0, 0.2, shape), 0, None), reference


def test_defaults_are_the_documented_conventions():
    x, y = small_pair()
    np.testing.assert_array_equal(tonemap(x), tonemap(x, "clip_gamma", 2.2))
    assert tonemap(x.astype(np.float32)).dtype == np.float64  # computed in float64
    assert relmse(x, y) == relmse(x, y, 0.01)
    assert smape(x, y) == smape(x, y, 0.01)


def test_psnr_data_range_and_no_warning_on_identical_images():
    y = np.full((8, 10, 3), 0.5)
    assert psnr(y + 0.1, y, data_range=2.0) == pytest.approx(20.0 + 20 * np.log10(2.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # identical images must not reach skimage's division by zero
        assert psnr(y, y) == float("inf")


def test_ssim_parameters_reach_skimage():
    rng = np.random.default_rng(4)
    x = rng.uniform(0, 1, (15, 17, 3))
    y = np.clip(x + rng.normal(0, 0.1, x.shape), 0, 1)
    # sigma 1.0 spans 9 pixels in skimage; k1, k2 away from their defaults
    expected = reference_ssim(x, y, win_size=9, sigma=1.0, k1=0.02, k2=0.05, data_range=1.0)
    assert ssim(x, y, win_size=9, sigma=1.0, k1=0.02, k2=0.05) == pytest.approx(expected, rel=1e-9)
    # an image exactly one window wide has one valid window position
    square = x[:11, :11]
    assert ssim(square, y[:11, :11]) == pytest.approx(reference_ssim(square, y[:11, :11]), rel=1e-9)


def test_relmse_largest_allowed_crop():
    x, y = small_pair(shape=(10, 12, 3))
    # crop 4 of a 10-pixel side leaves 2 rows: allowed (2 * crop < 10)
    expected = np.mean((x[4:-4, 4:-4] - y[4:-4, 4:-4]) ** 2 / (y[4:-4, 4:-4] ** 2 + 0.01))
    assert relmse(x, y, 0.01, crop=4) == pytest.approx(expected)


def test_nonfinite_reference_is_named():
    bad = np.zeros((16, 20, 3))
    bad[0, 0, 0] = np.inf
    with pytest.raises(DataError) as excinfo:
        mse(np.zeros((16, 20, 3)), bad)
    one_line_error(excinfo, "reference image has 1 NaN/Inf")
    with pytest.raises(DataError) as excinfo:
        mse(bad, np.zeros((16, 20, 3)))
    one_line_error(excinfo, "image metrics: denoised image has 1 NaN/Inf")


def metrics_dict(**overrides):
    cfg = {
        "tonemap": "reinhard_gamma",
        "gamma": 2.0,
        "relmse_eps": 0.5,
        "relmse_crop": 1,
        "smape_eps": 0.3,
        "ssim": {"win_size": 9, "sigma": 1.0, "k1": 0.02, "k2": 0.05},
        "lpips": {"enabled": True, "trunk_weights": None, "lin_weights": None, "seed": 0},
        "flip": {"enabled": True, "mode": "ldr"},
    }
    return {**cfg, **overrides}


def test_image_metrics_passes_every_setting_through():
    """Non-default values for every key of the metrics section, each checked against a direct call."""
    x, y = small_pair()
    cfg = metrics_dict()
    m = image_metrics(x, y, cfg)
    x_ldr, y_ldr = tonemap(x, "reinhard_gamma", 2.0), tonemap(y, "reinhard_gamma", 2.0)
    assert m["psnr"] == pytest.approx(psnr(x_ldr, y_ldr))
    assert m["ssim"] == pytest.approx(ssim(x_ldr, y_ldr, win_size=9, sigma=1.0, k1=0.02, k2=0.05))
    assert m["relmse"] == pytest.approx(relmse(x, y, 0.5, 1))
    assert m["smape"] == pytest.approx(smape(x, y, 0.3))
    assert m["mse"] == pytest.approx(mse(x, y))
    assert m["energy"] == pytest.approx(energy(x, y)) and m["energy"] != 1.0
    assert m["lpips"] == pytest.approx(lpips_distance(lpips_model(cfg["lpips"]), x_ldr, y_ldr))
    assert m["flip"] == pytest.approx(flip(x_ldr, y_ldr, "ldr"))
    hdr = image_metrics(x, y, metrics_dict(flip={"enabled": True, "mode": "hdr"}, lpips={"enabled": False}))
    assert hdr["flip"] == pytest.approx(flip(x, y, "hdr")) and hdr["flip"] != pytest.approx(m["flip"])
    assert "lpips" not in hdr
    # a section without `enabled: true` is off
    off = image_metrics(x, y, metrics_dict(flip={"mode": "hdr"}, lpips={"seed": 0}))
    assert set(off) == {"psnr", "ssim", "relmse", "smape", "mse", "energy", "energy_error"}


def test_lpips_variant_names_the_model_that_is_used():
    assert (
        lpips_variant(metrics_dict())
        == lpips_model({"seed": 0}).variant
        == "vgg16-random(seed=0)+lin-uniform"
    )
    seedless = "vgg16-random(seed=0)+lin-uniform"  # the seed defaults to 0
    assert lpips_variant(metrics_dict(lpips={"enabled": True})) == lpips_model({}).variant == seedless
    assert lpips_model({"seed": 1}).variant == "vgg16-random(seed=1)+lin-uniform"
    assert lpips_variant(metrics_dict(lpips={"enabled": False})) is None
    assert lpips_variant({"flip": {"enabled": True}}) is None


@pytest.mark.parametrize(
    ("section", "key", "name"),
    [
        (None, "gamma", "metrics.gamma"),
        ("ssim", "k2", "metrics.ssim.k2"),
        ("flip", "mode", "metrics.flip.mode"),
    ],
)
def test_missing_metric_settings_name_their_full_key(section, key, name):
    cfg = metrics_dict(lpips={"enabled": False})
    if section is None:
        del cfg[key]
    else:
        cfg[section] = {k: v for k, v in cfg[section].items() if k != key}
    with pytest.raises(ConfigError) as excinfo:
        image_metrics(*small_pair(), cfg)
    one_line_error(excinfo, name)


def test_lpips_model_passes_the_configured_weights_and_caches_per_setting(monkeypatch):
    # The pretrained VGG16 / LPIPS files cannot be downloaded here, so a stand-in records what the
    # configured paths and seed become.
    from src.metrics import image

    made = []

    class RecordingLPIPS:
        def __init__(self, trunk_weights, lin_weights, seed):
            made.append((trunk_weights, lin_weights, seed))

        def float(self):
            return self

        def cpu(self):
            return self

    monkeypatch.setattr(image, "LPIPS", RecordingLPIPS)
    monkeypatch.setattr(image, "_LPIPS_CACHE", {})
    first = image.lpips_model(
        {"trunk_weights": Path("/w/vgg16.pth"), "lin_weights": "/w/vgg.pth", "seed": "3"}
    )
    assert made == [("/w/vgg16.pth", "/w/vgg.pth", 3)]
    again = image.lpips_model({"trunk_weights": "/w/vgg16.pth", "lin_weights": Path("/w/vgg.pth"), "seed": 3})
    assert again is first and len(made) == 1  # the same setting, however spelt: built once
    image.lpips_model({})
    image.lpips_model({"trunk_weights": None, "lin_weights": None, "seed": 1})
    assert made[1:] == [(None, None, 0), (None, None, 1)]


# Surviving mutants of src/metrics/image.py (bash scripts/mutation.sh metrics), all equivalent here:
# - _check_pair: one of x, y left un-cast (dtype=None / default, 4 mutants): the other one is float64 and
#   every metric combines the two (x - y, skimage's float conversion), so numpy computes in float64 anyway.
# - psnr `float("inf")` -> `float("INF")`: the same value.
# - ssim `win_size=win_size` -> None / dropped: with gaussian_weights skimage derives the window from sigma,
#   and _check_ssim_window has already required win_size to be exactly that footprint.
# - ssim `use_sample_covariance=False` -> None: falsy, the same population covariance.
# - _enabled: `hasattr(cfg, "get") or True` (dict and DictConfig both have get); `.get("enabled", False)`
#   -> None / no default (`not None` is `not False`).
# - image_metrics `flip(x, y, mode)` -> `flip(x, y)` in the hdr branch: "hdr" is flip's default mode.
