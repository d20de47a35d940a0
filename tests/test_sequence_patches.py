"""Importance-sampled patch sequences (issue 16): shapes, consecutive in-range windows, bias towards a
region hard in only some frames at the cpu and paper sizes, easy windows still sampled, extraction equal
to slicing, determinism, one-line config errors."""

import numpy as np
import pytest

from src.data.patch_sampling import patch_means
from src.data.sequence_patches import (
    extract_sequence_patches,
    sample_sequence_patches,
    window_importance,
)
from src.errors import ConfigError, DataError
from tests.conftest import one_line_error

HARD_FRAMES = [6, 7]  # of F = 8: only windows starting at 4 or 5 (k = 3) see them


def hard_sequence(f, h, w):
    """Importance 0.02 everywhere, 1 in the left quarter of the columns of `HARD_FRAMES` only."""
    imp = np.full((f, h, w), 0.02)
    imp[HARD_FRAMES, :, : w // 4] = 1.0
    return imp


def hard_shares(f, h, w, p, k, n, seeds):
    """(share of samples whose window meets a hard frame and whose centre is in the hard quarter, the
    same share for uniform (start, corner) pairs, share of samples whose window meets no hard frame)."""
    hard_frame = np.isin(np.arange(f), HARD_FRAMES)
    win_hard = np.array([hard_frame[s : s + k].any() for s in range(f - k + 1)])
    col_hard = np.arange(w - p + 1) + p // 2 < w // 4
    imp = hard_sequence(f, h, w)
    hits, easy = [], []
    for seed in seeds:
        starts, corners = sample_sequence_patches(imp, p, n, k, seed)
        assert len(starts) == n
        hits.append(win_hard[starts] & col_hard[corners[:, 1]])
        easy.append(~win_hard[starts])
    return np.concatenate(hits).mean(), win_hard.mean() * col_hard.mean(), np.concatenate(easy).mean()


@pytest.mark.parametrize(
    "f, h, w, p, k, n, seeds",
    [(8, 72, 128, 32, 3, 24, range(20)), (8, 720, 1280, 65, 3, 400, range(2))],
    ids=["cpu", "paper"],
)
def test_sequences_favour_a_region_hard_in_some_frames_and_still_sample_easy_ones(f, h, w, p, k, n, seeds):
    share, uniform, easy_windows = hard_shares(f, h, w, p, k, n, seeds)
    assert share >= 2 * uniform  # measured: cpu 0.208 vs 0.055, paper 0.286 vs 0.079
    assert 1 - share >= 0.1  # easy crops still appear
    assert easy_windows >= 0.05  # and so do windows that never see a hard frame (measured 0.55, 0.50)


def test_shapes_consecutive_in_range_and_sorted():
    f, h, w, p, k, n = 6, 40, 56, 12, 4, 30
    imp = np.random.default_rng(0).random((f, h, w))
    starts, corners = sample_sequence_patches(imp, p, n, k, 1)
    assert starts.shape == (n,) and corners.shape == (n, 2)
    assert starts.dtype == corners.dtype == np.int64
    frames_used = starts[:, None] + np.arange(k)
    assert (frames_used >= 0).all() and (frames_used < f).all()
    assert (np.diff(frames_used, axis=1) == 1).all()
    assert (corners >= 0).all() and (corners[:, 0] + p <= h).all() and (corners[:, 1] + p <= w).all()
    keys = np.stack([starts, corners[:, 0], corners[:, 1]], axis=1)
    assert len({tuple(x) for x in keys}) == n  # distinct samples
    np.testing.assert_array_equal(np.lexsort(keys[:, ::-1].T), np.arange(n))  # sorted start, row, col
    s1, c1 = sample_sequence_patches(imp, p, n, 1, 1)  # k = 1: single frames, any of the F
    assert s1.max() <= f - 1 and len(s1) == n
    sf, _ = sample_sequence_patches(imp, p, n, f, 1)  # k = F: the one window
    assert not sf.any()


def test_deterministic_given_the_rng():
    imp = np.random.default_rng(2).random((5, 33, 47))
    a = sample_sequence_patches(imp, 8, 20, 2, np.random.default_rng(7))
    b = sample_sequence_patches(imp, 8, 20, 2, 7)
    for x, y in zip(a, b, strict=True):
        np.testing.assert_array_equal(x, y)
    c = sample_sequence_patches(imp, 8, 20, 2, 8)
    assert not (np.array_equal(a[0], c[0]) and np.array_equal(a[1], c[1]))


def test_tiny_frames_give_distinct_start_corner_pairs():
    # 4 crop positions per frame, 3 windows: 12 pairs for 10 samples (40 candidates asked)
    starts, corners = sample_sequence_patches(np.ones((4, 9, 9)), 8, 10, 2, 0)
    assert len({(s, r, c) for s, (r, c) in zip(starts, corners, strict=True)}) == 10
    starts, _ = sample_sequence_patches(np.ones((4, 9, 9)), 8, 50, 2, 0)
    assert len(starts) == 12  # only 12 exist


def test_window_importance_is_the_mean_over_the_window_of_patch_means():
    rng = np.random.default_rng(3)
    imp = rng.random((7, 20, 30))
    starts, corners = np.array([0, 2, 4]), np.array([[0, 0], [5, 11], [15, 25]])
    got = window_importance(imp, 5, 3, starts, corners)
    for i, (s, (r, c)) in enumerate(zip(starts, corners, strict=True)):
        assert got[i] == pytest.approx(imp[s : s + 3, r : r + 5, c : c + 5].mean())
        assert got[i] == pytest.approx(np.mean([patch_means(imp[t], 5)[r, c] for t in range(s, s + 3)]))


def test_extracted_sequences_equal_direct_slicing():
    f, h, w, c, p, k = 6, 23, 31, 3, 7, 3
    frames = np.random.default_rng(4).random((f, h, w, c)).astype(np.float32)
    starts, corners = sample_sequence_patches(frames.mean(-1), p, 12, k, 5)
    out = extract_sequence_patches(frames, starts, corners, p, k)
    assert out.shape == (12, k, p, p, c) and out.dtype == np.float32
    for i in (0, 5, 11):
        s, (r, cc) = starts[i], corners[i]
        np.testing.assert_array_equal(out[i], frames[s : s + k, r : r + p, cc : cc + p])
    assert extract_sequence_patches(frames, starts[:0], corners[:0], p, k).shape == (0, k, p, p, c)
    with pytest.raises(DataError, match="outside"):
        extract_sequence_patches(frames, np.array([f - k + 1]), np.array([[0, 0]]), p, k)
    with pytest.raises(DataError, match="outside"):
        extract_sequence_patches(frames, np.array([0]), np.array([[0, w - p + 1]]), p, k)


@pytest.mark.parametrize(
    "patch, k, needles",
    [
        (8, 5, ("dataset.preprocess.sequence_frames=5", "4 frames")),
        (8, 0, ("dataset.preprocess.sequence_frames=0", ">= 1")),
        (30, 2, ("task.preprocess.patch_size=30", "20x25")),
        (0, 2, ("task.preprocess.patch_size=0", ">= 1")),
    ],
)
def test_bad_arguments_are_one_line_config_errors_naming_the_key(patch, k, needles):
    imp = np.ones((4, 20, 25))
    with pytest.raises(ConfigError) as excinfo:
        sample_sequence_patches(imp, patch, 10, k, 0)
    one_line_error(excinfo, *needles)
    with pytest.raises(ConfigError) as excinfo:
        extract_sequence_patches(np.ones((4, 20, 25, 2)), np.zeros(1, int), np.zeros((1, 2), int), patch, k)
    one_line_error(excinfo, *needles)
    with pytest.raises(ConfigError) as excinfo:
        sample_sequence_patches(imp, 8, 10, 2, 0, min_keep_prob=1.5)
    one_line_error(excinfo, "task.preprocess.min_keep_prob=1.5")
