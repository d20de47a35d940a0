"""The range transforms a denoiser's colour goes through, and back, for numpy arrays and torch tensors:

- the KPCN split of still images (Bako et al. 2017 Sec. 4.1, Eqs. 3-4; the Zagreb thesis, Bunjevac 2019
  Sec. 4.3): the diffuse colour over the albedo, log(1 + s) of the specular, their variances to first
  order, and `rebuild_color`, which makes linear colour of the two again;
- the log-modulus sign(x) log(1 + |x|) of the volumetric sequences (Zhu et al. 2023), and its inverse,
  chosen by `dataset.preprocess.volume_transform` (`volume_transform`).

Pure functions shared by preprocessing, the networks, the objectives and the colour spaces
(`src/data/color_spaces.py`): this module imports none of them.
"""

from __future__ import annotations

import numpy as np

from src.errors import ConfigError


def _exp_minus_one(x):
    """exp(x) - 1 for numpy arrays and torch tensors alike (expm1: exact inverse of log1p)."""
    return np.expm1(x) if isinstance(x, np.ndarray | np.generic | float) else x.expm1()


def transform_diffuse(diffuse: np.ndarray, albedo: np.ndarray, eps: float) -> np.ndarray:
    """Bako et al. 2017 Eq. (3): d' = d / (albedo + eps), per RGB channel.

    Dividing out the (texture) albedo leaves the smooth irradiance; eps (0.00316 in the paper) avoids
    dividing by zero on black surfaces.
    """
    return diffuse / (albedo + eps)


def transform_diffuse_variance(var: np.ndarray, albedo: np.ndarray, eps: float) -> np.ndarray:
    """Variance of d / (albedo + eps): var / (mean_c(albedo) + eps)^2.

    Exact for a fixed albedo (Var(aX) = a^2 Var(X)) per channel. Since `var` is one channel (the mean over
    RGB of per-channel variances), the per-channel factors 1/(albedo_c + eps)^2 are replaced by one factor
    using the channel-mean albedo: an approximation, exact for grey albedo.
    """
    return var / (albedo.mean(axis=-1, keepdims=True) + eps) ** 2


def transform_specular(specular: np.ndarray) -> np.ndarray:
    """Bako et al. 2017 Eq. (4): s' = log(1 + s) (log1p, accurate for small s)."""
    return np.log1p(specular)


def transform_specular_variance(var: np.ndarray, specular: np.ndarray) -> np.ndarray:
    """Variance of log(1 + s) to first order (delta method): var / (1 + mean_c(s))^2.

    d/ds log(1 + s) = 1 / (1 + s), evaluated at the RAW (untransformed) specular s. Public repos that use
    the already log-transformed value, or (s + 1e-5)^2, get the wrong scale (tested against Monte Carlo).
    `var` is one channel, so s is replaced by its channel mean (exact for grey specular).
    """
    return var / (1.0 + specular.mean(axis=-1, keepdims=True)) ** 2


#: Guard of the thesis author's code against dividing by log(1 + 0) = 0.
THESIS_SPECULAR_EPS = 1e-5


def transform_specular_variance_thesis(var: np.ndarray, specular: np.ndarray) -> np.ndarray:
    """The seed thesis's propagation (Bunjevac 2019, Sec. 4.3): var / (log(1 + s))^2, as its author's
    code computes it, var / (log1p(s) + 1e-5)^2 (s: channel mean).

    It divides by the square of the *transformed* value rather than by the derivative's inverse
    (1 + s)^2, so it differs from the first-order variance by up to several hundred times for small or
    large s; offered only to replicate the thesis exactly (`dataset.preprocess.specular_variance=thesis`).
    """
    return var / (np.log1p(specular.mean(axis=-1, keepdims=True)) + THESIS_SPECULAR_EPS) ** 2


#: `dataset.preprocess.specular_variance` choices: the first-order (delta-method) propagation, or the seed
#: thesis's formula as its author's code computes it (for exact replication).
SPECULAR_VARIANCES = {"delta": transform_specular_variance, "thesis": transform_specular_variance_thesis}


def rebuild_color(diffuse_t, specular_t, albedo, eps: float):
    """Inverse of the two transforms: c = (albedo + eps) * d' + exp(s') - 1.

    Works on numpy arrays and torch tensors (training calls it on network outputs).
    """
    return (albedo + eps) * diffuse_t + _exp_minus_one(specular_t)


def _is_numpy(x) -> bool:
    return isinstance(x, np.ndarray | np.generic | float | int)


def _split_signs(x):
    """(x where x >= 0 else 0, -x where x < 0 else 0, x >= 0) of a torch tensor, by `where`, whose
    gradient reaches the selected value also at x = 0 (torch's clamp and relu give 0 there)."""
    nonneg = x >= 0
    zero = x.new_zeros(())
    return x.where(nonneg, zero), (-x).where(~nonneg, zero), nonneg


def log_modulus(x):
    """The log-modulus transform sign(x) log(1 + |x|), for numpy arrays and torch tensors.

    The input transform of the volumetric U-Net KPCN in Zhu, Zhang, Röthlin, Papas and Meyer, "Denoising
    Production Volumetric Rendering" (SIGGRAPH 2023 Talks): like log(1 + s) it compresses the dynamic
    range, and it also takes signed values (gradients, motion, centred features). Equal to log1p(x) for
    x >= 0, odd, slope 1 at 0. Each branch only sees its own sign's values (numpy: no overflow warning
    from the branch not taken); for torch via `_split_signs` rather than sign(x) * log1p(|x|): the same
    values, but autograd gives the true slope 1 at x = 0 (through sign and abs, or clamp, it gives 0).
    """
    if _is_numpy(x):
        x = np.asarray(x)
        return np.where(x >= 0, np.log1p(np.maximum(x, 0)), -np.log1p(np.maximum(-x, 0)))
    pos, neg, nonneg = _split_signs(x)
    return pos.log1p().where(nonneg, -neg.log1p())


def inverse_log_modulus(y):
    """Inverse of `log_modulus`: sign(y) (exp(|y|) - 1) (expm1, exact inverse of log1p); numpy or torch."""
    if _is_numpy(y):
        y = np.asarray(y)
        return np.where(y >= 0, np.expm1(np.maximum(y, 0)), -np.expm1(np.maximum(-y, 0)))
    pos, neg, nonneg = _split_signs(y)
    return pos.expm1().where(nonneg, -neg.expm1())


def log_modulus_variance(var: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Variance of log_modulus(x) to first order (delta method): var / (1 + mean_c(|x|))^2.

    d/dx log_modulus(x) = 1 / (1 + |x|), at the RAW (untransformed) value, as `transform_specular_variance`
    for log(1 + s), which this equals for x >= 0 (Zhu et al. 2023's log-modulus input transform, see
    `log_modulus`). `var` is one channel, so |x| is replaced by its channel mean (exact for grey x).
    """
    return var / (1.0 + np.abs(x).mean(axis=-1, keepdims=True)) ** 2


#: `dataset.preprocess.volume_transform` choices: Zhu et al. 2023's sign(x) log(1 + |x|), or linear.
VOLUME_TRANSFORMS = ("log_modulus", "none")


TRANSFORM_KEY = "dataset.preprocess.volume_transform"


def check_volume_transform(transform: str) -> None:
    if transform not in VOLUME_TRANSFORMS:
        raise ConfigError(f"{TRANSFORM_KEY}={transform!r}: expected one of {list(VOLUME_TRANSFORMS)}")


def volume_transform(x, transform: str):
    """The radiance transform `transform` names (numpy or torch): log_modulus, or none (identity)."""
    check_volume_transform(transform)
    return log_modulus(x) if transform == "log_modulus" else x


def inverse_volume_transform(y, transform: str):
    """Inverse of `volume_transform`: the linear radiance of a target or a network output."""
    check_volume_transform(transform)
    return inverse_log_modulus(y) if transform == "log_modulus" else y
