"""Importance-sampled training patches (Bunjevac 2019, Sec. 4.4; Bako et al. 2017, Sec. 5.1).

Most of a rendered image is easy to denoise (flat walls, background). Training on uniformly drawn patches
wastes steps there, so patch positions follow an importance map:

* `thesis_importance_map` (the default, `task.preprocess.importance: thesis`) is the seed thesis's map,
  as Bako et al.'s released code computes it: the local variance, over a window of about a patch, of the
  noisy colour relative to its local mean and of the noisy normals; per buffer the maximum over the three
  channels, gamma 1/2.2 (a less peaky map), clipped to 1 and scaled by its maximum; the two summed and
  scaled to [0, 1]. It marks edges, texture and noise alike.
* `importance_map` (`importance: mc_variance`, the harness's earlier map) uses the renderer's per-pixel
  Monte Carlo variance of colour and normals instead: noise only, no edges.

Candidate positions are spread over the image by dart throwing, then pruned with a keep probability that
grows with the candidate patch's mean importance, floored at `min_keep_prob` so easy regions still appear
(the thesis's Fig. 4.5: uniform candidates, then fewer kept where the map is low).

Pruning only has an effect if there are clearly more candidates than patches to keep. With a fixed
minimum distance that is not guaranteed: random dart throwing jams at about 55 % disk coverage, so at
1280x720 with 400 patches of 65 and a minimum distance of half a patch only ~520 candidates fit where
1600 were asked for, ~400 of them are kept whatever their importance, and a hard quarter of the image got
31.5 % of the patches against 23.6 % for uniform sampling. Bako et al.'s code meets the same limit by
shrinking the dart radius whenever throwing stalls. Here the configured minimum distance is therefore an
upper bound: `fitting_distance` lowers it so that the `candidates_factor * n` candidates cover at most
30 % of the image (well short of jamming), and `dart_throw` shrinks it further (by 0.96, Bako's rate) if a
batch of proposals still stalls. The candidate count then depends on `candidates_factor` alone, at every
image and patch size, and pruning selects by importance everywhere (tests: a hard quarter gets more than
twice its area share at both the paper and the cpu profile, and easy regions keep some patches).
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy import ndimage

from src.errors import ConfigError

#: Importance maps `task.preprocess.importance` can name.
IMPORTANCE_MAPS = ("thesis", "mc_variance")
#: Bako et al.'s floor on the squared local mean in the relative variance (their `relvar` metric).
RELATIVE_MEAN2_FLOOR = 1e-2
#: Relative size of E[x^2] - E[x]^2 below which a local variance is round-off (float64 eps ~2e-16).
ROUNDOFF = 1e-12
#: Largest share of the image the candidates' minimum-distance disks may cover (`fitting_distance`).
CANDIDATE_COVERAGE = 0.3
#: Dart radius factor after a stalled batch of proposals (Bako et al.'s code uses the same rate).
SHRINK_RATE = 0.96


def _as_plane(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 3 and x.shape[2] == 1:
        x = x[..., 0]
    if x.ndim != 2:
        raise ConfigError(f"{name}: expected (H, W) or (H, W, 1), got shape {x.shape}")
    return x


def _as_image(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 2:
        x = x[..., None]
    if x.ndim != 3:
        raise ConfigError(f"{name}: expected (H, W) or (H, W, C), got shape {x.shape}")
    return x


def _robust_unit(x: np.ndarray, percentile: float) -> np.ndarray:
    """x / percentile(x) clipped to [0, 1] (max instead when the percentile is 0; all zero stays zero).

    A percentile rather than the max, so a few fireflies do not squash every other pixel towards 0.
    """
    scale = float(np.percentile(x, percentile))
    if scale <= 0.0:
        scale = float(x.max())
    if scale <= 0.0:
        return np.zeros_like(x)
    return np.clip(x / scale, 0.0, 1.0)


def _unit_max(x: np.ndarray) -> np.ndarray:
    """x / max(x); all zero stays zero."""
    top = float(x.max()) if x.size else 0.0
    return x / top if top > 0.0 else np.zeros_like(x)


def importance_map(
    color_variance: np.ndarray, normal_variance: np.ndarray, *, percentile: float = 99.0
) -> np.ndarray:
    """The `mc_variance` map: per-pixel importance in [0, 1], shape (H, W):

        I = 0.5 * (min(cv / P(cv), 1) + min(nv / P(nv), 1))

    with cv, nv the (one-channel) Monte Carlo colour and normal variances of the pixel mean and P(.) their
    `percentile`-th percentile over the image. Each term is normalised on its own, so the two buffers
    count equally whatever their units (colour variance is HDR, normal variance is at most ~1).
    """
    cv = _as_plane(color_variance, "color_variance")
    nv = _as_plane(normal_variance, "normal_variance")
    if cv.shape != nv.shape:
        raise ConfigError(f"importance_map: colour variance {cv.shape} vs normal variance {nv.shape}")
    if not 0.0 < percentile <= 100.0:
        raise ConfigError(f"importance_map: percentile must be in (0, 100], got {percentile}")
    return 0.5 * (_robust_unit(cv, percentile) + _robust_unit(nv, percentile))


def window_pixels(window: float, patch_size: int) -> int:
    """The local-variance window in pixels for `window` patch sizes: rounded to the nearest odd count
    (a centred window), at least 1."""
    px = max(1, round(float(window) * int(patch_size)))
    return px if px % 2 else px + 1


def check_importance(importance: str) -> None:
    """A one-line ConfigError unless `task.preprocess.importance` names one of `IMPORTANCE_MAPS`."""
    if importance not in IMPORTANCE_MAPS:
        raise ConfigError(
            f"task.preprocess.importance={importance!r}: expected one of {list(IMPORTANCE_MAPS)}"
        )


def configured_importance_map(noisy: Mapping[str, np.ndarray], sampling: Mapping[str, Any]) -> np.ndarray:
    """The importance map `sampling["importance"]` names for one noisy image or frame, (H, W) in [0, 1]:
    `thesis` (the local variance of `noisy["color"]` and `noisy["normal"]` over
    `sampling["importance_window"]` patch sizes of `sampling["patch_size"]`) or `mc_variance` (their Monte
    Carlo variances `colorVariance` / `normalVariance`, at `sampling["importance_percentile"]`). The still
    images' and the volumetric sequences' preprocessing both sample by it."""
    if sampling["importance"] == "thesis":
        window = window_pixels(sampling["importance_window"], sampling["patch_size"])
        return thesis_importance_map(noisy["color"], noisy["normal"], window)
    return importance_map(
        noisy["colorVariance"], noisy["normalVariance"], percentile=sampling["importance_percentile"]
    )


def local_variance(x: np.ndarray, window: int, *, relative: bool = False) -> np.ndarray:
    """Per-channel variance of `x` (H, W, C) over the window x window neighbourhood of every pixel,
    E[x^2] - E[x]^2 with box means (scipy `uniform_filter`, mirrored borders); values within round-off
    of 0 (below 1e-12 E[x^2]) are 0, so a constant image gives exactly 0.

    relative: divided by max(local mean^2, 1e-2), i.e. the variance of x relative to its local mean
    (Bako et al.'s `relvar`, so bright and dark regions of the same relative noise count the same).
    """
    x = _as_image(x, "local_variance")
    if int(window) < 1:
        raise ConfigError(f"local_variance: window must be >= 1 pixel, got {window}")
    size = (int(window), int(window), 1)
    mean = ndimage.uniform_filter(x, size=size, mode="reflect")
    mean_sq = ndimage.uniform_filter(x * x, size=size, mode="reflect")
    var = mean_sq - mean * mean
    # Round-off of the difference (~1e-16 E[x^2]) is not variance: gamma 1/2.2 and the scaling by the
    # maximum would otherwise turn it into a map of noise on a flat image.
    var = np.where(var > ROUNDOFF * mean_sq, var, 0.0)
    if relative:
        var = var / np.maximum(mean * mean, RELATIVE_MEAN2_FLOOR)
    return var


def variance_map(x: np.ndarray, window: int, *, relative: bool = False) -> np.ndarray:
    """One buffer's term of the thesis map, (H, W) in [0, 1]: the maximum over channels of
    `local_variance`, to the power 1/2.2, clipped to 1, divided by its maximum (all zero stays zero)."""
    v = local_variance(x, window, relative=relative).max(axis=2)
    return _unit_max(np.minimum(v ** (1.0 / 2.2), 1.0))


def thesis_importance_map(color: np.ndarray, normal: np.ndarray, window: int) -> np.ndarray:
    """The `thesis` map (Bunjevac 2019, Sec. 4.4 and Fig. 4.4; Bako et al. 2017, Sec. 5.1), (H, W) in
    [0, 1]:

        I = unit(variance_map(color, relative) + variance_map(normal)),   unit(x) = x / max(x)

    `color` (H, W, 3) the noisy colour, `normal` (H, W, 3) the noisy normals, `window` the local-variance
    window in pixels. The thesis states the sum of the colour and normal variances, each the maximum over
    its three components, normalised to [0, 1]; the window (Bako's code: the patch size), the relative
    colour variance and the gamma 1/2.2 are those of Bako et al.'s code, which the thesis follows. A
    constant image gives 0 everywhere.
    """
    c, n = _as_image(color, "color"), _as_image(normal, "normal")
    if c.shape[:2] != n.shape[:2]:
        raise ConfigError(f"thesis_importance_map: colour {c.shape} vs normal {n.shape}")
    return _unit_max(variance_map(c, window, relative=True) + variance_map(n, window))


def patch_means(importance: np.ndarray, patch_size: int) -> np.ndarray:
    """Mean of `importance` over every patch_size^2 window, indexed by top-left corner:
    shape (H - P + 1, W - P + 1). Summed-area table: O(H W) whatever the patch size."""
    p = patch_size
    sat = np.zeros((importance.shape[0] + 1, importance.shape[1] + 1), dtype=np.float64)
    sat[1:, 1:] = importance.cumsum(axis=0).cumsum(axis=1)
    return (sat[p:, p:] - sat[:-p, p:] - sat[p:, :-p] + sat[:-p, :-p]) / (p * p)


def fitting_distance(
    n_rows: int, n_cols: int, n: int, cap: float, coverage: float = CANDIDATE_COVERAGE
) -> float:
    """min(cap, d) with d the distance at which `n` points' disks of diameter d cover `coverage` of the
    n_rows x n_cols domain: n * pi d^2 / 4 = coverage * n_rows * n_cols. Random dart throwing jams near
    0.55 coverage, so at 0.3 the `n` points are reached quickly."""
    if n <= 0:
        return float(cap)
    return min(float(cap), math.sqrt(4.0 * coverage * n_rows * n_cols / (math.pi * n)))


def dart_throw(
    n_rows: int,
    n_cols: int,
    n: int,
    min_distance: float,
    rng: np.random.Generator,
    max_attempts: int,
    shrink: float | None = None,
) -> np.ndarray:
    """Up to `n` distinct integer points in [0, n_rows) x [0, n_cols), pairwise >= the current minimum
    distance apart (Euclidean).

    Uniform proposals in batches (vectorised): a proposal is rejected if closer than the distance to an
    accepted point or to an earlier proposal of its batch that passed the first test (so every accepted
    pair is far enough apart). With `shrink` (0 < shrink < 1), the distance is multiplied by it after a
    batch that accepts under 2 % of its proposals (the domain is nearly full at that distance); points
    accepted before keep their larger spacing. Stops after `max_attempts` proposals, so fewer than `n`
    points can come back.
    """
    n = min(int(n), n_rows * n_cols)
    accepted = np.empty((0, 2), dtype=np.int64)
    attempts, r2 = 0, float(min_distance) ** 2
    while len(accepted) < n and attempts < max_attempts:
        need = n - len(accepted)
        batch = min(max(2 * need, 64), 1024, max_attempts - attempts)
        attempts += batch
        prop = np.stack([rng.integers(0, n_rows, batch), rng.integers(0, n_cols, batch)], axis=1)
        if r2 > 0:
            if len(accepted):
                d2 = (prop[:, None, 0] - accepted[None, :, 0]) ** 2 + (
                    prop[:, None, 1] - accepted[None, :, 1]
                ) ** 2
                prop = prop[d2.min(axis=1) >= r2]
            d2 = (prop[:, None, 0] - prop[None, :, 0]) ** 2 + (prop[:, None, 1] - prop[None, :, 1]) ** 2
            prop = prop[~np.triu(d2 < r2, k=1).any(axis=0)]
        else:  # no spacing: distinct points only
            prop = np.unique(prop, axis=0)
            if len(accepted):
                keys = accepted[:, 0] * n_cols + accepted[:, 1]
                prop = prop[~np.isin(prop[:, 0] * n_cols + prop[:, 1], keys)]
            prop = prop[rng.permutation(len(prop))]
        accepted = np.concatenate([accepted, prop[:need]])
        if shrink is not None and len(prop) < 0.02 * batch and len(accepted) < n:
            r2 *= shrink * shrink
    return accepted


def _candidates_and_kept(
    importance: np.ndarray,
    patch_size: int,
    n_patches: int,
    rng: np.random.Generator | int,
    candidates_factor: float,
    min_keep_prob: float,
    min_distance: float | None,
) -> tuple[np.ndarray, np.ndarray]:
    imp = _as_plane(importance, "importance")
    h, w = imp.shape
    p = int(patch_size)
    if p < 1 or p > h or p > w:
        raise ConfigError(f"patch_size {patch_size} does not fit the {h}x{w} image")
    if n_patches < 0 or candidates_factor < 1.0:
        raise ConfigError(f"n_patches {n_patches} must be >= 0, candidates_factor {candidates_factor} >= 1")
    if not 0.0 <= min_keep_prob <= 1.0:
        raise ConfigError(f"min_keep_prob must be in [0, 1], got {min_keep_prob}")
    rng = np.random.default_rng(rng) if not isinstance(rng, np.random.Generator) else rng
    min_distance = p / 2 if min_distance is None else float(min_distance)
    empty = np.zeros((0, 2), dtype=np.int64)
    if n_patches == 0:
        return empty, empty

    n_rows, n_cols = h - p + 1, w - p + 1
    n_cand = min(math.ceil(n_patches * candidates_factor), n_rows * n_cols)
    distance = fitting_distance(n_rows, n_cols, n_cand, min_distance)
    cand = dart_throw(
        n_rows, n_cols, n_cand, distance, rng, max_attempts=50 * n_cand + 1000, shrink=SHRINK_RATE
    )
    means = patch_means(imp, p)[cand[:, 0], cand[:, 1]]
    corners = cand[prune_candidates(means, n_patches, min_keep_prob, rng)]
    return cand, corners[np.lexsort((corners[:, 1], corners[:, 0]))]


def prune_candidates(means: np.ndarray, n: int, min_keep_prob: float, rng: np.random.Generator) -> np.ndarray:
    """Indices of the (at most) `n` candidates kept, given their mean importances `means` (steps 2-3 of
    `sample_patches`): candidate i is kept with probability max(m_i / max_j m_j, min_keep_prob) (all 1
    when every mean is 0); if more than `n` survive, a uniform subset of them; if fewer, the rest drawn
    from the pruned ones with probability proportional to their keep probability."""
    top = means.max()
    keep_prob = np.maximum(means / top if top > 0 else np.ones_like(means), min_keep_prob)
    keep = rng.random(len(means)) < keep_prob
    kept, rest = np.flatnonzero(keep), np.flatnonzero(~keep)
    if len(kept) >= n:
        return rng.choice(kept, n, replace=False)
    n_fill = min(n - len(kept), len(rest))
    w_rest = keep_prob[rest]
    w_rest = w_rest / w_rest.sum() if w_rest.sum() > 0 else None
    return np.concatenate([kept, rng.choice(rest, n_fill, replace=False, p=w_rest)])


def sample_patches(
    importance: np.ndarray,
    patch_size: int,
    n_patches: int,
    rng: np.random.Generator | int,
    candidates_factor: float = 4.0,
    min_keep_prob: float = 0.1,
    min_distance: float | None = None,
    *,
    return_candidates: bool = False,
) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Top-left corners (n, 2) as (row, col) int64 of importance-sampled patches, all inside the image.

    1. Dart throwing: ceil(n_patches * candidates_factor) candidate corners (at most one per position),
       pairwise at least `fitting_distance(..., min_distance)` apart, shrunk further if throwing stalls
       (`min_distance` default patch_size / 2: an upper bound, see the module docstring).
    2. Pruning: candidate i is kept with probability max(m_i / max_j m_j, min_keep_prob), m_i its patch's
       mean importance (summed-area table), so the hardest candidates are always kept and easy regions
       still appear.
    3. If more than n_patches survive, a uniform subset of them (this keeps the importance weighting); if
       fewer, the rest are drawn from the pruned candidates with probability proportional to their keep
       probability. Only if the image has fewer than n_patches positions are fewer returned.

    Deterministic given `rng` (a Generator, or an int seed); corners are sorted (row, then column).
    With `return_candidates`, (corners, candidates) (candidates in throwing order), for figures.
    """
    cand, corners = _candidates_and_kept(
        importance, patch_size, n_patches, rng, candidates_factor, min_keep_prob, min_distance
    )
    return (corners, cand) if return_candidates else corners


def extract_patches(image: np.ndarray, corners: np.ndarray, patch_size: int) -> np.ndarray:
    """Gather (N, P, P, C) patches of an (H, W, C) image at top-left `corners` (fancy indexing, no loop)."""
    offs = np.arange(patch_size)
    rows = corners[:, 0, None] + offs  # (N, P)
    cols = corners[:, 1, None] + offs
    return image[rows[:, :, None], cols[:, None, :]]


def save_sampling_figure(
    path: str | os.PathLike[str],
    importance: np.ndarray,
    candidates: np.ndarray,
    kept: np.ndarray,
    patch_size: int,
    title: str = "",
) -> None:
    """One PNG, three panels like the thesis's Figs. 4.4-4.5: the importance map (darker = more
    important), the candidate patch centres, the kept ones. Written atomically (Agg canvas, no pyplot)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from src.io.atomic import atomic_path

    imp = _as_plane(importance, "importance")
    h, w = imp.shape
    fig = Figure(figsize=(15, 5 * h / w + 0.8), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 3)
    half = (patch_size - 1) / 2
    panels = (
        ("importance map", None),
        (f"{len(candidates)} candidates", candidates),
        (f"{len(kept)} kept", kept),
    )
    for ax, (label, pts) in zip(axes, panels, strict=True):
        ax.imshow(imp, cmap="gray_r", vmin=0.0, vmax=1.0, interpolation="nearest")
        if pts is not None and len(pts):
            ax.scatter(pts[:, 1] + half, pts[:, 0] + half, s=4, c="tab:red", linewidths=0)
        ax.set_title(label)
        ax.set_axis_off()
    if title:
        fig.suptitle(title)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=100)
