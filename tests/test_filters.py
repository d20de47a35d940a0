"""Non-learned denoising baselines: the cross-bilateral filter and the OIDN wrapper."""

import numpy as np
import pytest
import torch
from scipy import ndimage

from src.errors import ConfigError
from src.models.filters.cross_bilateral import CrossBilateralFilter
from src.models.filters.oidn import OIDNDenoiser
from src.models.instantiate import build_method
from tests.conftest import compose_config, one_line_error

HUGE = 1e8  # a feature sigma so large that the feature has no influence on the weights


def make_batch(color, normal=None, albedo=None, depth=None):
    """Batch dict of float32 tensors; missing guides are constant (so they do not change the weights)."""
    n, _, h, w = color.shape
    normal = (
        normal if normal is not None else np.broadcast_to([0, 0, 1.0], (n, h, w, 3)).transpose(0, 3, 1, 2)
    )
    albedo = albedo if albedo is not None else np.full((n, 3, h, w), 0.5)
    depth = depth if depth is not None else np.full((n, 1, h, w), 0.3)
    arrays = {"color": color, "normal": normal, "albedo": albedo, "depth": depth}
    return {k: torch.from_numpy(np.ascontiguousarray(v, dtype=np.float32)) for k, v in arrays.items()}


def bilateral(radius=3, spatial=1.5, color=HUGE, normal=HUGE, albedo=HUGE, depth=HUGE):
    return CrossBilateralFilter(radius, spatial, color, normal, albedo, depth)


def test_constant_image_is_preserved_whatever_the_guides():
    rng = np.random.default_rng(0)
    color = np.full((1, 3, 9, 14), 0.7)
    batch = make_batch(color, rng.uniform(-1, 1, (1, 3, 9, 14)), rng.uniform(0, 1, (1, 3, 9, 14)))
    out = bilateral(radius=2, color=0.5, normal=0.3, albedo=0.1, depth=0.05)(batch)["color"]
    np.testing.assert_allclose(out.numpy(), color, atol=1e-6)


def test_huge_feature_sigmas_give_a_normalised_gaussian_blur_with_replicate_borders():
    rng = np.random.default_rng(1)
    radius, spatial = 3, 1.7
    color = rng.uniform(0, 4, (1, 3, 13, 19))  # non-square, HDR values
    out = bilateral(radius, spatial)(make_batch(color))["color"].numpy()
    # Independent reference: scipy correlation with a normalised truncated Gaussian, 'nearest' borders.
    offsets = np.arange(-radius, radius + 1)
    kernel = np.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * spatial**2))
    kernel /= kernel.sum()
    expected = np.stack([ndimage.correlate(color[0, c], kernel, mode="nearest") for c in range(3)])
    np.testing.assert_allclose(out[0], expected, rtol=1e-5, atol=1e-5)


def test_normal_edge_is_preserved_unlike_a_plain_blur():
    rng = np.random.default_rng(2)
    h, w, edge = 16, 24, 12
    clean = np.where(np.arange(w) < edge, 0.2, 1.0)[None, None, None, :] * np.ones((1, 3, h, w))
    noisy = clean + rng.normal(0, 0.05, clean.shape)
    normal = np.zeros((1, 3, h, w))
    normal[:, 2, :, :edge] = 1.0  # left half faces +z, right half +x: a crease
    normal[:, 0, :, edge:] = 1.0
    batch = make_batch(noisy, normal=normal)
    guided = bilateral(radius=4, spatial=3.0, normal=0.1)(batch)["color"].numpy()
    blurred = bilateral(radius=4, spatial=3.0)(batch)["color"].numpy()
    band = slice(edge - 3, edge + 3)  # the columns next to the edge, where a blur bleeds
    err_guided = np.abs(guided - clean)[..., band].mean()
    err_blurred = np.abs(blurred - clean)[..., band].mean()
    assert err_guided < 0.2 * err_blurred, (err_guided, err_blurred)
    assert err_guided < 0.03


def test_output_shape_dtype_and_halo():
    rng = np.random.default_rng(3)
    color = rng.uniform(0, 1, (2, 3, 7, 11))
    filt = bilateral(radius=2, color=0.5, normal=0.3, albedo=0.1, depth=0.05)
    out = filt(make_batch(color, depth=rng.uniform(0, 1, (2, 1, 7, 11))))
    assert set(out) == {"color"}
    assert out["color"].shape == (2, 3, 7, 11) and out["color"].dtype == torch.float32
    assert filt.halo == 2 and filt.learned is False
    assert filt.flops_per_pixel() == 38 * 25 + 16


def test_cross_bilateral_from_the_real_config_and_missing_key():
    cfg = compose_config(["model=cross_bilateral"]).model
    filt = build_method(cfg)
    assert isinstance(filt, CrossBilateralFilter) and filt.halo == cfg.radius
    assert filt.sigmas["depth"] == cfg.sigma_depth
    partial = {k: v for k, v in cfg.items() if k != "sigma_depth"}
    with pytest.raises(ConfigError) as excinfo:
        build_method(partial)
    one_line_error(excinfo, "model.sigma_depth", "missing")
    with pytest.raises(ConfigError) as excinfo:
        build_method({**cfg, "sigma_color": 0.0})
    one_line_error(excinfo, "model.sigma_color", "> 0")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_cross_bilateral_on_gpu_matches_cpu():
    rng = np.random.default_rng(4)
    batch = make_batch(rng.uniform(0, 2, (1, 3, 12, 17)), depth=rng.uniform(0, 1, (1, 1, 12, 17)))
    filt = bilateral(radius=3, color=0.5, depth=0.05)
    cpu = filt(batch)["color"]
    gpu = filt({k: v.cuda() for k, v in batch.items()})["color"]
    assert gpu.is_cuda
    np.testing.assert_allclose(gpu.cpu().numpy(), cpu.numpy(), rtol=1e-4, atol=1e-5)


def test_oidn_reduces_error_on_a_noisy_gradient_and_keeps_shape():
    rng = np.random.default_rng(5)
    h, w = 40, 56
    ramp = np.linspace(0.1, 0.9, w)[None, :] * np.linspace(0.5, 1.0, h)[:, None]
    reference = np.broadcast_to(ramp, (1, 3, h, w)).copy()
    noisy = np.clip(reference + rng.normal(0, 0.1, reference.shape), 0, None)
    denoiser = build_method(compose_config(["model=oidn"]).model)
    out = denoiser(make_batch(noisy))["color"]
    assert out.shape == (1, 3, h, w) and out.dtype == torch.float32
    assert denoiser.halo is None and denoiser.learned is False
    mse_noisy = np.mean((noisy - reference) ** 2)
    mse_out = np.mean((out.numpy() - reference) ** 2)
    assert mse_out < 0.25 * mse_noisy, (mse_out, mse_noisy)


def test_oidn_defaults_and_bad_values():
    cfg = dict(compose_config(["model=oidn"]).model)
    del cfg["quality"]
    assert build_method({**cfg, "quality": "fast"}).quality == "fast"
    assert build_method(cfg).quality == "high"  # an omitted key takes the constructor's default
    with pytest.raises(ConfigError) as excinfo:
        build_method({**cfg, "hdr": "yes"})
    one_line_error(excinfo, "model.hdr", "expected bool", "'yes'")
    with pytest.raises(ConfigError) as excinfo:
        OIDNDenoiser(quality="best")
    one_line_error(excinfo, "model.quality")
    with pytest.raises(ConfigError) as excinfo:
        OIDNDenoiser(use_albedo=False, use_normal=True)
    one_line_error(excinfo, "model.use_normal")
