"""Full-reference image metrics on float numpy arrays of shape (H, W, 3).

Conventions (the `metrics:` section of conf/config.yaml; defaults here mirror it):
- HDR colour is tone-mapped (`tonemap`) before the LDR metrics PSNR and SSIM, with data range 1.
- relMSE, SMAPE, MSE and energy are computed on linear HDR values.
- Per-channel errors are averaged over all pixels and channels (no luminance weighting).
- SSIM follows dm_pix / TensorFlow: 11x11 Gaussian window with sigma 1.5, K1 = 0.01, K2 = 0.03,
  population (not sample) covariance, "valid" window positions only, mean over channels.
- LPIPS (src/metrics/lpips.py, torchvision VGG16) on the tone-mapped images scaled to [-1, 1], on the CPU
  in float32; the variant (trunk and linear weights) is reported by `lpips_variant`.
- FLIP (src/metrics/flip.py) in `metrics.flip.mode`: hdr on linear colour, ldr on the tone-mapped image.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from src.errors import ConfigError, DataError, require
from src.metrics.flip import flip
from src.metrics.lpips import LPIPS, lpips_distance

TONEMAPS = ("clip_gamma", "reinhard_gamma", "clip")
#: skimage's Gaussian filter truncates at 3.5 sigma (fixed inside `structural_similarity`).
SKIMAGE_GAUSSIAN_TRUNCATE = 3.5


def tonemap(x: np.ndarray, method: str = "clip_gamma", gamma: float = 2.2) -> np.ndarray:
    """Linear HDR -> display values in [0, 1].

    clip_gamma:     clip(x, 0, 1) ** (1 / gamma)
    reinhard_gamma: (max(x, 0) / (1 + max(x, 0))) ** (1 / gamma)   (Reinhard et al. 2002, global operator)
    clip:           clip(x, 0, 1), for images already display-encoded (NeRF's sRGB views); no gamma
    """
    x = np.asarray(x, dtype=np.float64)
    if method == "clip_gamma":
        base = np.clip(x, 0.0, 1.0)
    elif method == "reinhard_gamma":
        pos = np.maximum(x, 0.0)
        base = pos / (1.0 + pos)
    elif method == "clip":
        return np.clip(x, 0.0, 1.0)
    else:
        raise ConfigError(f"metrics.tonemap={method!r}; expected one of {', '.join(TONEMAPS)}")
    return base ** (1.0 / gamma)


def _check_pair(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Both as float64 arrays; a one-line DataError when shapes differ or a value is NaN/Inf."""
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if x.shape != y.shape:
        raise DataError(f"image metrics: shapes differ, denoised {x.shape} vs reference {y.shape}")
    for name, a in (("denoised", x), ("reference", y)):
        if not np.isfinite(a).all():
            raise DataError(
                f"image metrics: {name} image has {np.count_nonzero(~np.isfinite(a))} NaN/Inf values"
            )
    return x, y


def mse(x: np.ndarray, y: np.ndarray) -> float:
    """Mean squared error mean((x - y)^2) over all pixels and channels."""
    x, y = _check_pair(x, y)
    return float(np.mean((x - y) ** 2))


def psnr(x: np.ndarray, y: np.ndarray, data_range: float = 1.0) -> float:
    """PSNR = 10 log10(data_range^2 / MSE) in dB (skimage), on tone-mapped values; y is the reference.
    Identical images give +inf."""
    x, y = _check_pair(x, y)
    if np.array_equal(x, y):
        return float("inf")  # skimage would divide by zero and warn
    return float(peak_signal_noise_ratio(y, x, data_range=data_range))


def _check_ssim_window(win_size: int, sigma: float) -> None:
    """skimage's Gaussian always spans 2 * int(3.5 sigma + 0.5) + 1 pixels and uses `win_size` only to
    crop the borders; the dm_pix convention needs both to be the same window, so refuse a mismatch."""
    footprint = 2 * int(SKIMAGE_GAUSSIAN_TRUNCATE * sigma + 0.5) + 1
    if win_size != footprint:
        raise ConfigError(
            f"metrics.ssim.win_size={win_size} but a Gaussian of sigma {sigma} spans {footprint} pixels "
            f"in skimage; use win_size={footprint} or change sigma"
        )


def ssim(
    x: np.ndarray,
    y: np.ndarray,
    win_size: int = 11,
    sigma: float = 1.5,
    k1: float = 0.01,
    k2: float = 0.03,
    data_range: float = 1.0,
) -> float:
    """Mean SSIM (Wang et al. 2004, Eq. 13) of (H, W, C) images, dm_pix / TensorFlow convention.

    skimage `structural_similarity` with gaussian_weights=True (normalised Gaussian window of `sigma`,
    `win_size` wide), use_sample_covariance=False (population covariance), channel_axis=-1 (per-channel
    SSIM, then averaged), C1 = (k1 L)^2, C2 = (k2 L)^2 with L = data_range. The SSIM map is cropped by
    (win_size - 1) // 2 pixels on each side before the mean, i.e. only fully covered windows count.
    """
    x, y = _check_pair(x, y)
    _check_ssim_window(win_size, sigma)
    if min(x.shape[:2]) < win_size:
        raise DataError(f"ssim: image {x.shape[0]}x{x.shape[1]} is smaller than the {win_size}-pixel window")
    value = structural_similarity(
        x,
        y,
        win_size=win_size,
        gaussian_weights=True,
        sigma=sigma,
        K1=k1,
        K2=k2,
        use_sample_covariance=False,
        data_range=data_range,
        channel_axis=-1,
    )
    return float(value)


def relmse(x: np.ndarray, y: np.ndarray, eps: float = 0.01, crop: int = 0) -> float:
    """Relative MSE mean((x - y)^2 / (y^2 + eps)) on linear HDR, y the reference (Rousselle et al. 2011);
    per channel, averaged over all channels and pixels.

    `crop` pixels are dropped at every border first. The two common conventions are eps = 0.01 with no
    crop (Bako et al. 2017, the default here) and eps = 1e-4 with a border crop (e.g. 32 px; Vogels et al.
    2018 and OIDN's scripts), which keeps filter border artefacts out of a metric that small eps makes
    sensitive to dark pixels."""
    x, y = _check_pair(x, y)
    if crop < 0 or 2 * crop >= min(y.shape[:2]):
        raise ConfigError(
            f"metrics.relmse_crop: {crop} px leaves nothing of a {y.shape[1]}x{y.shape[0]} image; "
            "expected 0 <= crop < half the shorter side"
        )
    if crop:
        x, y = x[crop:-crop, crop:-crop], y[crop:-crop, crop:-crop]
    return float(np.mean((x - y) ** 2 / (y**2 + eps)))


def relmse_spp(x: np.ndarray, y: np.ndarray, spp: int, eps: float = 0.01) -> float:
    """Relative MSE as the GP filter thesis defines it (Davletaliyev 2016, Eq. 3.5, after Rousselle et al.
    2011 and Kalantari et al. 2015): (1/N) sum_i (m/2) sum_{q in rgb} (x_iq - y_iq)^2 / (y_iq^2 + eps),
    with N pixels and m = `spp` the input's samples per pixel. Summed (not averaged) over the channels and
    scaled by m/2, it is 1.5 m times `relmse` with the same eps; the factor cancels in the thesis's
    fitness, relmse_spp(filtered) / relmse_spp(noisy) (`relmse_ratio`)."""
    x, y = _check_pair(x, y)
    if spp < 1:
        raise ValueError(f"relmse_spp: spp must be >= 1, got {spp}")
    return float(0.5 * spp * np.mean(np.sum((x - y) ** 2 / (y**2 + eps), axis=-1)))


def smape(x: np.ndarray, y: np.ndarray, eps: float = 0.01) -> float:
    """Symmetric mean absolute percentage error mean(|x - y| / (|x| + |y| + eps)) on linear HDR (Vogels et
    al. 2018); per channel, averaged over all channels and pixels."""
    x, y = _check_pair(x, y)
    return float(np.mean(np.abs(x - y) / (np.abs(x) + np.abs(y) + eps)))


def energy(x: np.ndarray, y: np.ndarray) -> float:
    """Energy mean(x) / mean(y) over all pixels and channels, on linear HDR, y the reference: 1.0 for the
    truth, below 1 for an output that darkens the image. relMSE and PSNR can reward a filter that darkens
    (a dark output sits close to the reference's dark, noisy-to-estimate pixels), so the GP filter studies
    report it beside them. NaN where the reference's mean is not positive (an all-black frame): the ratio
    has no meaning there, and one such frame must not stop a whole evaluation; an output with a negative
    mean gives a negative energy, reported as it is."""
    x, y = _check_pair(x, y)
    reference_mean = float(np.mean(y))
    return float(np.mean(x)) / reference_mean if reference_mean > 0.0 else float("nan")


def energy_error(x: np.ndarray, y: np.ndarray) -> float:
    """|energy(x, y) - 1|: how far one image's brightness is from the reference's, in either direction.
    A run's mean energy lets a brighter and a darker image cancel; the mean of this per-image error does not,
    so it measures a colour (brightness) shift such as direct prediction's (Bunjevac 2019, Fig. 6.11)."""
    return abs(energy(x, y) - 1.0)


def _get(cfg: Mapping[str, Any], key: str, prefix: str = "metrics") -> Any:
    return require(cfg, key, prefix)


#: LPIPS models by (trunk_weights, lin_weights, seed), built on first use (VGG16 takes a moment).
_LPIPS_CACHE: dict[tuple[str | None, str | None, int], LPIPS] = {}


def _enabled(metrics_cfg: Mapping[str, Any], name: str) -> Mapping[str, Any] | None:
    """The `metrics.<name>` section when present and enabled, else None."""
    section = metrics_cfg.get(name) if hasattr(metrics_cfg, "get") else None
    if section is None or not section.get("enabled", False):
        return None
    return section


def lpips_model(lpips_cfg: Mapping[str, Any]) -> LPIPS:
    """The cached CPU LPIPS model for `metrics.lpips` {trunk_weights, lin_weights, seed}."""
    trunk, lin = lpips_cfg.get("trunk_weights"), lpips_cfg.get("lin_weights")
    key = (
        None if trunk is None else str(trunk),
        None if lin is None else str(lin),
        int(lpips_cfg.get("seed", 0)),
    )
    if key not in _LPIPS_CACHE:
        _LPIPS_CACHE[key] = LPIPS(trunk_weights=key[0], lin_weights=key[1], seed=key[2]).float().cpu()
    return _LPIPS_CACHE[key]


def lpips_variant(metrics_cfg: Mapping[str, Any]) -> str | None:
    """The LPIPS variant string (e.g. "vgg16-random(seed=0)+lin-uniform"), or None when LPIPS is off."""
    section = _enabled(metrics_cfg, "lpips")
    return None if section is None else lpips_model(section).variant


def image_metrics(
    denoised: np.ndarray, reference: np.ndarray, metrics_cfg: Mapping[str, Any]
) -> dict[str, float]:
    """psnr, ssim (both on tone-mapped values), relmse, smape, mse, energy, energy_error (linear HDR) of one
    image pair,
    plus lpips (tone-mapped) and flip (per `metrics.flip.mode`) when enabled.

    `metrics_cfg` is the `metrics:` config section (DictConfig or dict): tonemap, gamma, relmse_eps,
    relmse_crop, smape_eps, ssim {win_size, sigma, k1, k2}, optionally lpips {enabled, trunk_weights,
    lin_weights, seed} and flip {enabled, mode}.
    """
    x, y = _check_pair(denoised, reference)
    keys = ("tonemap", "gamma", "relmse_eps", "relmse_crop", "smape_eps")
    method, gamma, eps, crop, smape_eps = (_get(metrics_cfg, k) for k in keys)
    ssim_cfg = _get(metrics_cfg, "ssim")
    ssim_args = {k: _get(ssim_cfg, k, "metrics.ssim") for k in ("win_size", "sigma", "k1", "k2")}
    x_ldr, y_ldr = tonemap(x, method, gamma), tonemap(y, method, gamma)
    out = {
        "psnr": psnr(x_ldr, y_ldr),
        "ssim": ssim(x_ldr, y_ldr, **ssim_args),
        "relmse": relmse(x, y, eps, crop),
        "smape": smape(x, y, smape_eps),
        "mse": mse(x, y),
        "energy": energy(x, y),
        "energy_error": energy_error(x, y),
    }
    lpips_cfg = _enabled(metrics_cfg, "lpips")
    if lpips_cfg is not None:
        with torch.no_grad():
            out["lpips"] = lpips_distance(lpips_model(lpips_cfg), x_ldr, y_ldr)
    flip_cfg = _enabled(metrics_cfg, "flip")
    if flip_cfg is not None:
        mode = _get(flip_cfg, "mode", "metrics.flip")
        out["flip"] = flip(x, y, mode) if mode == "hdr" else flip(x_ldr, y_ldr, mode)
    return out
