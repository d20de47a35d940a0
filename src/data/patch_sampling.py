"""Importance-sampled training patches (Bako et al. 2017 Sec. 5.1; the seed thesis does the same).

Most of a rendered image is easy to denoise (flat walls, background). Training on uniformly drawn patches
wastes steps there, so candidate patch positions are first spread over the image by dart throwing (a
Poisson-disk-like set: no two candidates closer than a minimum distance), then pruned with a keep
probability that grows with the patch's mean importance (colour and normal variance: noise and geometric
detail). A floor on the keep probability keeps some easy patches, so the network still sees flat regions.
"""

from __future__ import annotations

import math

import numpy as np

from src.errors import ConfigError


def _as_plane(x: np.ndarray, name: str) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 3 and x.shape[2] == 1:
        x = x[..., 0]
    if x.ndim != 2:
        raise ConfigError(f"{name}: expected (H, W) or (H, W, 1), got shape {x.shape}")
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


def importance_map(
    color_variance: np.ndarray, normal_variance: np.ndarray, *, percentile: float = 99.0
) -> np.ndarray:
    """Per-pixel importance in [0, 1], shape (H, W):

        I = 0.5 * (min(cv / P(cv), 1) + min(nv / P(nv), 1))

    with cv, nv the (one-channel) colour and normal variances of the pixel mean and P(.) their
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


def patch_means(importance: np.ndarray, patch_size: int) -> np.ndarray:
    """Mean of `importance` over every patch_size^2 window, indexed by top-left corner:
    shape (H - P + 1, W - P + 1). Summed-area table: O(H W) whatever the patch size."""
    p = patch_size
    sat = np.zeros((importance.shape[0] + 1, importance.shape[1] + 1), dtype=np.float64)
    sat[1:, 1:] = importance.cumsum(axis=0).cumsum(axis=1)
    return (sat[p:, p:] - sat[:-p, p:] - sat[p:, :-p] + sat[:-p, :-p]) / (p * p)


def dart_throw(
    n_rows: int, n_cols: int, n: int, min_distance: float, rng: np.random.Generator, max_attempts: int
) -> np.ndarray:
    """Up to `n` integer points in [0, n_rows) x [0, n_cols), pairwise >= min_distance apart (Euclidean).

    Uniform proposals, each rejected if closer than min_distance to an accepted point; stops after
    `max_attempts` proposals (the domain may be full), so fewer than n points can come back.
    """
    accepted = np.empty((n, 2), dtype=np.int64)
    k, attempts, r2 = 0, 0, float(min_distance) ** 2
    while k < n and attempts < max_attempts:
        batch = min(max(2 * (n - k), 64), max_attempts - attempts)
        attempts += batch
        proposals = np.stack([rng.integers(0, n_rows, batch), rng.integers(0, n_cols, batch)], axis=1)
        for p in proposals:
            if k and r2 > 0 and (((accepted[:k] - p) ** 2).sum(axis=1) < r2).any():
                continue
            accepted[k] = p
            k += 1
            if k == n:
                break
    return accepted[:k]


def sample_patches(
    importance: np.ndarray,
    patch_size: int,
    n_patches: int,
    rng: np.random.Generator | int,
    candidates_factor: float = 4.0,
    min_keep_prob: float = 0.1,
    min_distance: float | None = None,
) -> np.ndarray:
    """Top-left corners (n, 2) as (row, col) int64 of importance-sampled patches, all inside the image.

    1. Dart throwing: ceil(n_patches * candidates_factor) candidate corners, pairwise at least
       `min_distance` apart (default patch_size / 2: overlap allowed, near-duplicates not).
    2. Pruning: candidate i is kept with probability max(m_i / max_j m_j, min_keep_prob), m_i its patch's
       mean importance (summed-area table), so the hardest candidates are always kept and easy regions
       still appear.
    3. If more than n_patches survive, a uniform subset of them (this keeps the importance weighting); if
       fewer, the rest are drawn from the pruned candidates with probability proportional to their keep
       probability. Only if dart throwing found fewer than n_patches candidates (the image is too small
       for that many at min_distance) are fewer than n_patches returned.

    Deterministic given `rng` (a Generator, or an int seed); corners are sorted (row, then column).
    """
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
    if n_patches == 0:
        return np.zeros((0, 2), dtype=np.int64)

    n_cand = math.ceil(n_patches * candidates_factor)
    cand = dart_throw(h - p + 1, w - p + 1, n_cand, min_distance, rng, max_attempts=30 * n_cand)
    means = patch_means(imp, p)[cand[:, 0], cand[:, 1]]
    top = means.max()
    keep_prob = np.maximum(means / top if top > 0 else np.ones_like(means), min_keep_prob)
    keep = rng.random(len(cand)) < keep_prob
    kept, rest = np.flatnonzero(keep), np.flatnonzero(~keep)
    if len(kept) >= n_patches:
        chosen = rng.choice(kept, n_patches, replace=False)
    else:
        n_fill = min(n_patches - len(kept), len(rest))
        w_rest = keep_prob[rest]
        w_rest = w_rest / w_rest.sum() if w_rest.sum() > 0 else None
        chosen = np.concatenate([kept, rng.choice(rest, n_fill, replace=False, p=w_rest)])
    corners = cand[chosen]
    return corners[np.lexsort((corners[:, 1], corners[:, 0]))]


def extract_patches(image: np.ndarray, corners: np.ndarray, patch_size: int) -> np.ndarray:
    """Gather (N, P, P, C) patches of an (H, W, C) image at top-left `corners` (fancy indexing, no loop)."""
    offs = np.arange(patch_size)
    rows = corners[:, 0, None] + offs  # (N, P)
    cols = corners[:, 1, None] + offs
    return image[rows[:, :, None], cols[:, None, :]]
