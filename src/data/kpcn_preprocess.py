"""KPCN input/target preprocessing (Bako et al. 2017, "Kernel-Predicting Convolutional Networks for
Denoising Monte Carlo Renderings", Sec. 4.1; same transforms in the seed thesis).

The image is split into a diffuse and a specular component, each denoised by its own branch:

- diffuse:  d' = d / (albedo + eps)   (untextured irradiance: smoother, easier to denoise)
- specular: s' = log(1 + s)           (compresses the high dynamic range of highlights)

and put back together by `rebuild_color`: c = (albedo + eps) * d' + exp(s') - 1.

All functions are pure, take float arrays of shape (H, W, C) and keep that layout (channel last). The
variance buffers are one-channel variances *of the pixel mean* (mean over RGB of the per-channel ones),
so they are propagated through the transforms to first order (delta method), using channel means of the
colour-valued quantities; see the individual docstrings.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from src.data.features import FEATURE_BUFFERS
from src.data.kpcn_buffers import KPCN_BUFFERS
from src.data.transforms import (
    SPECULAR_VARIANCES,
    transform_diffuse,
    transform_diffuse_variance,
    transform_specular,
)
from src.errors import ConfigError, DataError
from src.io.atomic import atomic_write_json

#: Buffers `make_network_inputs` needs, with their channel counts (from the KPCN convention).
REQUIRED_BUFFERS = {
    b: len(KPCN_BUFFERS[b])
    for b in ("diffuse", "specular", "albedo", "normal", "depth", "visibility")
    + ("diffuseVariance", "specularVariance", "albedoVariance", "normalVariance", "depthVariance")
    + ("visibilityVariance",)
}

#: The GP filters' buffers (Davletaliyev 2016, Sec. 3.2.1.2), optional in a KPCN file (real KPCN data lack
#: them), with their channel counts, and the key each is stored under (`src.data.shards`).
GP_FEATURE_BUFFERS = {
    b: len(KPCN_BUFFERS[b])
    for b in ("position", "positionVariance", "secondary_albedo", "secondary_albedoVariance")
}
GP_FEATURE_KEYS = {
    "position": "position",
    "positionVariance": "position_var",
    "secondary_albedo": "secondary_albedo",
    "secondary_albedoVariance": "secondary_albedo_var",
}


def gp_feature_arrays(buffers: Mapping[str, np.ndarray], what: str = "noisy image") -> dict[str, np.ndarray]:
    """The GP filters' features of one image, float32 (H, W, C), unnormalised (the filter normalises per
    image): {"position", "position_var", "secondary_albedo", "secondary_albedo_var"} when the buffers have
    all of `GP_FEATURE_BUFFERS`, {} when they have none (real KPCN data, older renders); a one-line
    DataError for only some of them."""
    present = [b for b in GP_FEATURE_BUFFERS if b in buffers]
    if not present:
        return {}
    _check_buffers(buffers, GP_FEATURE_BUFFERS, what)
    return {GP_FEATURE_KEYS[b]: np.asarray(buffers[b], dtype=np.float32) for b in GP_FEATURE_BUFFERS}


def normalize_depth(depth: np.ndarray, var: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Scale depth into [0, 1] by its per-image maximum (Bako et al. 2017 Sec. 4.1); variance / max^2.

    Makes the feature independent of the scene's units. An all-zero depth (max 0) stays zero.
    """
    m = float(depth.max()) if depth.size else 0.0
    if m <= 0.0:
        return np.zeros_like(depth), np.zeros_like(var)
    return depth / m, var / (m * m)


def image_gradients(x: np.ndarray) -> np.ndarray:
    """Backward differences: dx[:, j] = x[:, j] - x[:, j-1], dy[i] = x[i] - x[i-1], zero at the first
    column / row. Returns concat(dx, dy) along channels: (H, W, 2C).

    Bako et al. feed the x/y gradients of every feature so the network sees edges directly.
    """
    dx = np.zeros_like(x)
    dy = np.zeros_like(x)
    dx[:, 1:] = x[:, 1:] - x[:, :-1]
    dy[1:] = x[1:] - x[:-1]
    return np.concatenate([dx, dy], axis=-1)


def _check_buffers(buffers: Mapping[str, np.ndarray], names: Iterable[str], what: str) -> tuple[int, int]:
    """Every needed buffer present, (H, W, C) with the right C, one shared H x W, finite."""
    shape = None
    for name in names:
        if name not in buffers:
            raise DataError(f"{what}: buffer '{name}' is missing (have {sorted(buffers)})")
        b = buffers[name]
        channels = REQUIRED_BUFFERS.get(name) or GP_FEATURE_BUFFERS[name]
        if b.ndim != 3 or b.shape[2] != channels:
            raise DataError(f"{what}: buffer '{name}' has shape {b.shape}, expected (H, W, {channels})")
        if shape is None:
            shape = b.shape[:2]
        elif b.shape[:2] != shape:
            raise DataError(f"{what}: buffer '{name}' is {b.shape[:2]}, other buffers are {shape}")
        if not np.isfinite(b).all():
            raise DataError(f"{what}: buffer '{name}' contains NaN or Inf")
    return shape


def _candidate_stack(color: tuple[np.ndarray, np.ndarray], guides: Mapping[str, tuple]) -> np.ndarray:
    """One branch's candidate features (order `CANDIDATE_CHANNELS`): for the branch colour and each guide
    buffer, its value, its variance and its image gradients."""
    parts = []
    for buffer in FEATURE_BUFFERS:
        value, var = color if buffer == "color" else guides[buffer]
        parts += [value, var, image_gradients(value)]
    return np.concatenate(parts, axis=-1)


def make_network_inputs(
    buffers: Mapping[str, np.ndarray], eps: float, specular_variance: str = "delta"
) -> dict[str, np.ndarray]:
    """Build both branches' candidate inputs (order: `CANDIDATE_CHANNELS`, from which a run selects
    `task.features`; see `src.data.features`) from one noisy image.

    Returns float32 arrays: `diffuse_in`, `specular_in` (H, W, 38), `diffuse_t`, `specular_t` (H, W, 3:
    the transformed noisy colours, = channels 0:3 of the inputs, what a KPCN kernel filters) and
    `albedo` (H, W, 3, needed by `rebuild_color`), `normal` (H, W, 3) and the normalised `depth` (H, W, 1)
    (the guides of the non-learned baselines). The auxiliary features are shared by both branches.
    `specular_variance` picks the specular branch's variance propagation (`SPECULAR_VARIANCES`).
    """
    _check_buffers(buffers, REQUIRED_BUFFERS, "noisy image")
    b = {k: np.asarray(buffers[k], dtype=np.float32) for k in REQUIRED_BUFFERS}
    albedo = b["albedo"]
    diffuse_t = transform_diffuse(b["diffuse"], albedo, eps)
    specular_t = transform_specular(b["specular"])
    depth, depth_var = normalize_depth(b["depth"], b["depthVariance"])
    guides = {
        "normal": (b["normal"], b["normalVariance"]),
        "depth": (depth, depth_var),
        "albedo": (albedo, b["albedoVariance"]),
        "visibility": (b["visibility"], b["visibilityVariance"]),
    }
    diffuse_var = transform_diffuse_variance(b["diffuseVariance"], albedo, eps)
    if specular_variance not in SPECULAR_VARIANCES:
        expected = list(SPECULAR_VARIANCES)
        raise ConfigError(
            f"dataset.preprocess.specular_variance={specular_variance!r}: expected one of {expected}"
        )
    specular_var = SPECULAR_VARIANCES[specular_variance](b["specularVariance"], b["specular"])
    out = {
        "diffuse_in": _candidate_stack((diffuse_t, diffuse_var), guides),
        "specular_in": _candidate_stack((specular_t, specular_var), guides),
        "diffuse_t": diffuse_t,
        "specular_t": specular_t,
        "albedo": albedo,
        "normal": b["normal"],
        "depth": depth,
    }
    return {k: v.astype(np.float32, copy=False) for k, v in out.items()}


def make_targets(
    reference_buffers: Mapping[str, np.ndarray], noisy_albedo: np.ndarray, eps: float
) -> dict[str, np.ndarray]:
    """Transformed reference: `diffuse_target` = ref diffuse / (noisy albedo + eps), `specular_target` =
    log(1 + ref specular), float32 (H, W, 3).

    Uses the reference's OWN diffuse and specular (one public notebook overwrote the reference specular
    with the noisy one, training the network to reproduce noise). The division uses the NOISY input's
    albedo because that is the albedo `rebuild_color` multiplies back at inference (the reference albedo
    is unknown then): with the same albedo, rebuild_color(targets) gives back the reference colour
    exactly, so a loss on the targets is a loss on the final image. (Albedo converges fast, so the two
    albedos are nearly equal anyway.)
    """
    _check_buffers(reference_buffers, ("diffuse", "specular"), "reference image")
    ref = {k: np.asarray(reference_buffers[k], dtype=np.float32) for k in ("diffuse", "specular")}
    if ref["diffuse"].shape != noisy_albedo.shape:
        raise DataError(f"reference is {ref['diffuse'].shape}, noisy albedo is {noisy_albedo.shape}")
    return {
        "diffuse_target": transform_diffuse(ref["diffuse"], noisy_albedo, eps).astype(np.float32),
        "specular_target": transform_specular(ref["specular"]).astype(np.float32),
    }


@dataclass(frozen=True)
class WhiteningStats:
    """Per-channel mean and std (float64, shape (C,)) of one branch's network input."""

    mean: np.ndarray
    std: np.ndarray

    def to_dict(self) -> dict[str, list[float]]:
        return {"mean": self.mean.tolist(), "std": self.std.tolist()}

    def select(self, channels: list[int]) -> WhiteningStats:
        """The statistics of the given channels only (the run's `task.features` among the stored)."""
        return WhiteningStats(self.mean[channels], self.std[channels])

    @classmethod
    def from_dict(cls, d: Mapping[str, list[float]]) -> WhiteningStats:
        return cls(np.asarray(d["mean"], dtype=np.float64), np.asarray(d["std"], dtype=np.float64))


class RunningMoments:
    """Streaming per-channel mean/variance (Chan et al. parallel update, float64).

    Merging batch moments avoids the catastrophic cancellation of sum(x^2)/n - mean^2 on HDR data.
    """

    def __init__(self) -> None:
        self.n = 0
        self.mean: np.ndarray | None = None
        self.m2: np.ndarray | None = None

    def update(self, x: np.ndarray, channel_axis: int = -1) -> None:
        x = np.moveaxis(np.asarray(x, dtype=np.float64), channel_axis, -1)
        x = x.reshape(-1, x.shape[-1])
        if x.shape[0] == 0:
            return
        n_b, mean_b = x.shape[0], x.mean(axis=0)
        m2_b = ((x - mean_b) ** 2).sum(axis=0)
        if self.mean is None:
            self.n, self.mean, self.m2 = n_b, mean_b, m2_b
            return
        if mean_b.shape != self.mean.shape:
            raise DataError(f"whitening: {mean_b.shape[0]} channels after {self.mean.shape[0]}")
        n = self.n + n_b
        delta = mean_b - self.mean
        self.mean = self.mean + delta * (n_b / n)
        self.m2 = self.m2 + m2_b + delta**2 * (self.n * n_b / n)
        self.n = n

    def finalize(self, std_eps: float) -> WhiteningStats:
        """Population std, floored at `std_eps` so constant channels do not blow up."""
        if self.mean is None:
            raise DataError("whitening: no training data to compute statistics from")
        std = np.sqrt(self.m2 / self.n)
        return WhiteningStats(self.mean.copy(), np.maximum(std, std_eps))


def compute_whitening_stats(arrays: Iterable[np.ndarray], std_eps: float) -> WhiteningStats:
    """Mean/std per channel over an iterable of (..., C) arrays, streamed (one array in memory at a time).

    Pass TRAINING-split data only: statistics from val/test would leak held-out data into the model.
    """
    acc = RunningMoments()
    for a in arrays:
        acc.update(a)
    return acc.finalize(std_eps)


def whiten(x, stats: WhiteningStats, channel_axis: int = -1):
    """(x - mean) / std per channel; numpy arrays or torch tensors (kept on their device/dtype)."""
    shape = [1] * x.ndim
    shape[channel_axis] = -1
    mean, std = stats.mean.reshape(shape), stats.std.reshape(shape)
    if isinstance(x, np.ndarray):
        return ((x - mean) / std).astype(x.dtype, copy=False)
    return (x - x.new_tensor(mean)) / x.new_tensor(std)


def save_whitening_stats(path: str | os.PathLike[str], stats: Mapping[str, WhiteningStats]) -> None:
    """Write {branch: {"mean": [...], "std": [...]}} as JSON (atomically)."""
    atomic_write_json(path, {k: v.to_dict() for k, v in stats.items()})


def load_whitening_stats(path: str | os.PathLike[str]) -> dict[str, WhiteningStats]:
    """Read what `save_whitening_stats` wrote."""
    try:
        payload = json.loads(Path(path).read_text())
        return {k: WhiteningStats.from_dict(v) for k, v in payload.items()}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise DataError(f"{path}: cannot read whitening statistics ({e})") from e
