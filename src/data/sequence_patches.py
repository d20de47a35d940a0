"""Importance-sampled training *sequences* of patches, for temporally stable denoisers (issue 16).

A denoiser trained with a temporal loss, which compares the differences between consecutive frames of
the output and of the reference (as the U-Net KPCN for volumes of Zhu, Zhang, Röthlin, Papas and Meyer,
"Denoising Production Volumetric Rendering", SIGGRAPH 2023 Talks), needs samples that are the SAME crop
over k consecutive frames. A sample is a window start s (frames s, ..., s + k - 1 of an F-frame
sequence) and one top-left corner (row, col) used for all k frames.

Sampling follows `patch_sampling.sample_patches`, with the window as a third coordinate:

* candidates: ceil(n * candidates_factor) corners dart-thrown over the frame exactly as for a single
  image (`fitting_distance` + `dart_throw`, so they stay spread at every image and patch size), each
  with a window start drawn uniformly from [0, F - k]. The spacing is spatial across all windows on
  purpose: windows overlap (s and s + 1 share k - 1 frames), so the same crop in two nearby windows
  would be a near-duplicate sample. Only when the frame has fewer crop positions than candidates (tiny
  frames, where spacing is moot) are the candidates distinct (start, corner) pairs drawn uniformly.
* importance of a candidate: the mean over the window's k frames of the patch-mean importance (one
  summed-area table per frame, `patch_means`), so a region that is hard in only some frames counts in
  the windows that contain them.
* pruning: `prune_candidates`, as for images: keep probability max(m / max m, min_keep_prob), so hard
  (window, crop) pairs are favoured and easy ones still appear.

All functions are pure and vectorised; `src.data.volume_shards` uses them for `stage=preprocess
dataset=volumetric`.
"""

from __future__ import annotations

import math

import numpy as np

from src.data.patch_sampling import (
    SHRINK_RATE,
    dart_throw,
    fitting_distance,
    patch_means,
    prune_candidates,
)
from src.errors import ConfigError, DataError

#: Config keys the arguments come from (named in errors).
FRAMES_KEY = "dataset.preprocess.sequence_frames"
PATCH_KEY = "task.preprocess.patch_size"
COUNT_KEY = "dataset.preprocess.patches_per_sequence"


def _check_window(n_frames: int, k: int) -> None:
    if isinstance(k, bool) or not isinstance(k, int | np.integer) or k < 1:
        raise ConfigError(f"{FRAMES_KEY}={k!r}: expected an integer >= 1")
    if k > n_frames:
        raise ConfigError(f"{FRAMES_KEY}={k} is more than the sequence's {n_frames} frames")


def _check_patch(patch_size: int, h: int, w: int) -> None:
    if isinstance(patch_size, bool) or not isinstance(patch_size, int | np.integer) or patch_size < 1:
        raise ConfigError(f"{PATCH_KEY}={patch_size!r}: expected an integer >= 1")
    if patch_size > h or patch_size > w:
        raise ConfigError(f"{PATCH_KEY}={patch_size} does not fit the {h}x{w} frames")


def window_importance(importance: np.ndarray, patch_size: int, k: int, starts, corners) -> np.ndarray:
    """Mean over frames [s, s + k) of the mean importance of the patch at `corners`, for each sample
    (starts (n,), corners (n, 2)): shape (n,). One summed-area table per frame, read at the corners only,
    then a running sum over frames."""
    per_frame = np.stack([patch_means(f, patch_size)[corners[:, 0], corners[:, 1]] for f in importance])
    csum = np.concatenate([np.zeros((1, len(starts))), per_frame.cumsum(axis=0)])
    cols = np.arange(len(starts))
    return (csum[starts + k, cols] - csum[starts, cols]) / k


def sample_sequence_patches(
    importance: np.ndarray,
    patch_size: int,
    n: int,
    k: int,
    rng: np.random.Generator | int,
    candidates_factor: float = 4.0,
    min_keep_prob: float = 0.1,
    min_distance: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """`n` importance-sampled training sequences: (starts (n,), corners (n, 2)), int64.

    Sample i covers frames starts[i], ..., starts[i] + k - 1 (all in [0, F)) of the importance map's
    (F, H, W) sequence, cropped at top-left corners[i] = (row, col) in every frame (the crop inside the
    frame). Candidates, window importance and pruning as in the module docstring; `candidates_factor`,
    `min_keep_prob` and `min_distance` (an upper bound on the candidates' spacing, default half a patch)
    mean what they mean for `sample_patches`. Fewer than `n` come back only if the sequence has fewer
    (window, corner) pairs. Deterministic given `rng` (a Generator or an int seed); sorted by start, then
    row, then column.
    """
    imp = np.asarray(importance, dtype=np.float64)
    if imp.ndim == 4 and imp.shape[3] == 1:
        imp = imp[..., 0]
    if imp.ndim != 3:
        raise DataError(f"importance: expected (F, H, W), got shape {imp.shape}")
    f, h, w = imp.shape
    _check_window(f, k)
    _check_patch(patch_size, h, w)
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
        raise ConfigError(f"{COUNT_KEY}={n!r}: expected an integer >= 0")
    if not candidates_factor >= 1.0:
        raise ConfigError(f"task.preprocess.candidates_factor={candidates_factor}: expected >= 1")
    if not 0.0 <= min_keep_prob <= 1.0:
        raise ConfigError(f"task.preprocess.min_keep_prob={min_keep_prob}: expected a value in [0, 1]")
    rng = rng if isinstance(rng, np.random.Generator) else np.random.default_rng(rng)
    p, k = int(patch_size), int(k)
    if n == 0:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 2), dtype=np.int64)

    n_starts, n_rows, n_cols = f - k + 1, h - p + 1, w - p + 1
    n_cand = min(math.ceil(n * candidates_factor), n_starts * n_rows * n_cols)
    if n_cand <= n_rows * n_cols:
        cap = p / 2 if min_distance is None else float(min_distance)
        distance = fitting_distance(n_rows, n_cols, n_cand, cap)
        corners = dart_throw(
            n_rows, n_cols, n_cand, distance, rng, max_attempts=50 * n_cand + 1000, shrink=SHRINK_RATE
        )
        starts = rng.integers(0, n_starts, len(corners))
    else:  # fewer crop positions than candidates: distinct (start, corner) pairs, uniformly
        flat = rng.choice(n_starts * n_rows * n_cols, n_cand, replace=False)
        starts, rows, cols = np.unravel_index(flat, (n_starts, n_rows, n_cols))
        corners = np.stack([rows, cols], axis=1)
    starts, corners = starts.astype(np.int64), corners.astype(np.int64)

    means = window_importance(imp, p, k, starts, corners)
    chosen = prune_candidates(means, n, min_keep_prob, rng)
    starts, corners = starts[chosen], corners[chosen]
    order = np.lexsort((corners[:, 1], corners[:, 0], starts))
    return starts[order], corners[order]


def extract_sequence_patches(
    frames: np.ndarray, starts: np.ndarray, corners: np.ndarray, patch_size: int, k: int
) -> np.ndarray:
    """Gather (n, k, P, P, C) patches of an (F, H, W, C) sequence: sample i is
    frames[starts[i] + j, r:r + P, c:c + P] for j < k, (r, c) = corners[i]. One fancy-indexing gather,
    no loop; dtype kept."""
    frames = np.asarray(frames)
    if frames.ndim != 4:
        raise DataError(f"frames: expected (F, H, W, C), got shape {frames.shape}")
    f, h, w, _ = frames.shape
    _check_window(f, k)
    _check_patch(patch_size, h, w)
    starts, corners = np.asarray(starts, dtype=np.int64), np.asarray(corners, dtype=np.int64)
    if starts.ndim != 1 or corners.shape != (len(starts), 2):
        raise DataError(f"starts {starts.shape} and corners {corners.shape}: expected (n,) and (n, 2)")
    if len(starts) and (
        starts.min() < 0
        or starts.max() + k > f
        or corners.min() < 0
        or corners[:, 0].max() + patch_size > h
        or corners[:, 1].max() + patch_size > w
    ):
        raise DataError(
            f"sequence patches of {k} frames of {patch_size}^2 reach outside the {f}x{h}x{w} frames"
        )
    offs = np.arange(patch_size)
    t = starts[:, None] + np.arange(k)  # (n, k)
    rows = corners[:, 0, None] + offs  # (n, P)
    cols = corners[:, 1, None] + offs
    return frames[t[:, :, None, None], rows[:, None, :, None], cols[:, None, None, :]]
