"""Importance-sampled patches: bias towards hard regions, coverage of easy ones, bounds, determinism."""

import numpy as np
import pytest

from src.data.patch_sampling import dart_throw, extract_patches, importance_map, patch_means, sample_patches
from src.errors import ConfigError

H, W, P = 96, 136, 8


def quadrant_importance():
    imp = np.full((H, W), 0.01)
    imp[: H // 2, : W // 2] = 1.0
    return imp


def test_importance_map_combines_both_normalised_buffers():
    rng = np.random.default_rng(0)
    cv, nv = 1e4 * rng.random((13, 21, 1)), 1e-3 * rng.random((13, 21))
    cv[0, 0] = 1e9  # a firefly does not squash the rest (percentile normalisation)
    imp = importance_map(cv, nv)
    assert imp.shape == (13, 21) and imp.min() >= 0 and imp.max() <= 1
    assert np.corrcoef(imp.ravel(), cv.ravel().clip(max=np.percentile(cv, 99)))[0, 1] > 0.5
    assert np.corrcoef(imp.ravel(), nv.ravel())[0, 1] > 0.5
    assert not importance_map(np.zeros((4, 5)), np.zeros((4, 5))).any()


def test_patch_means_match_brute_force():
    x = np.random.default_rng(1).random((9, 14))
    m = patch_means(x, 4)
    assert m.shape == (6, 11)
    assert np.isclose(m[2, 7], x[2:6, 7:11].mean()) and np.isclose(m[-1, -1], x[-4:, -4:].mean())


def test_sampling_prefers_important_quadrant_but_covers_the_rest():
    corners = sample_patches(quadrant_importance(), P, 60, np.random.default_rng(0), 4.0, min_keep_prob=0.1)
    assert corners.shape == (60, 2) and corners.dtype == np.int64
    centres = corners + P / 2
    in_quadrant = (centres[:, 0] < H / 2) & (centres[:, 1] < W / 2)
    assert in_quadrant.mean() > 0.5  # uniform sampling would give ~0.25
    assert (~in_quadrant).sum() >= 3  # easy regions still appear
    assert len({tuple(c) for c in corners}) == len(corners)


def test_deterministic_and_in_bounds_for_non_square_images():
    imp = np.random.default_rng(2).random((21, 37))
    a = sample_patches(imp, 5, 20, np.random.default_rng(7))
    b = sample_patches(imp, 5, 20, 7)
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, sample_patches(imp, 5, 20, 8))
    for h, w in ((21, 37), (37, 21)):
        c = sample_patches(np.ones((h, w)), 6, 15, 3, min_distance=1)
        assert len(c) == 15
        assert (c >= 0).all() and (c[:, 0] + 6 <= h).all() and (c[:, 1] + 6 <= w).all()
    patches = extract_patches(np.arange(21 * 37 * 2).reshape(21, 37, 2), a, 5)
    np.testing.assert_array_equal(
        patches[3], np.arange(21 * 37 * 2).reshape(21, 37, 2)[a[3, 0] : a[3, 0] + 5, a[3, 1] : a[3, 1] + 5]
    )


def test_dart_throwing_respects_min_distance():
    pts = dart_throw(50, 70, 40, 6.0, np.random.default_rng(3), max_attempts=5000)
    d = np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(-1)) + np.eye(len(pts)) * 1e9
    assert d.min() >= 6.0 and len(pts) == 40


def test_patch_larger_than_image_is_a_config_error():
    with pytest.raises(ConfigError, match="patch_size"):
        sample_patches(np.ones((13, 21)), 16, 4, 0)
    with pytest.raises(ConfigError, match="min_keep_prob"):
        sample_patches(np.ones((13, 21)), 4, 4, 0, min_keep_prob=1.5)
