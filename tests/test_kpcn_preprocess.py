"""KPCN transforms: inverse, variance propagation vs Monte Carlo, gradients, candidate inputs, targets,
whitening."""

import numpy as np
import pytest
import torch

from src.data.features import CANDIDATE_CHANNELS
from src.data.kpcn_preprocess import (
    compute_whitening_stats,
    image_gradients,
    load_whitening_stats,
    make_network_inputs,
    make_targets,
    normalize_depth,
    save_whitening_stats,
    whiten,
)
from src.data.transforms import (
    inverse_log_modulus,
    log_modulus,
    log_modulus_variance,
    rebuild_color,
    transform_diffuse,
    transform_diffuse_variance,
    transform_specular,
    transform_specular_variance,
    transform_specular_variance_thesis,
)
from src.errors import ConfigError, DataError
from tests.conftest import one_line_error

EPS = 0.00316


def synthetic_buffers(h=13, w=21, seed=0, noise=0.1):
    """A random KPCN buffer dict (float32, channel last), color = diffuse + specular."""
    rng = np.random.default_rng(seed)
    f = lambda *s: rng.random((h, w, *s), dtype=np.float32)  # noqa: E731
    albedo = 0.05 + 0.9 * f(3)
    diffuse = albedo * (0.2 + 3 * f(3)) * (1 + noise * f(3))
    specular = 5 * f(3) ** 4
    normal = f(3) * 2 - 1
    b = {
        "diffuse": diffuse,
        "specular": specular,
        "color": diffuse + specular,
        "albedo": albedo,
        "normal": normal / np.linalg.norm(normal, axis=-1, keepdims=True),
        "depth": 1 + 10 * f(1),
        "visibility": f(1),
    }
    for k in ("color", "diffuse", "specular", "albedo", "normal", "depth", "visibility"):
        b[f"{k}Variance"] = noise * f(1)
    return b


def test_inverse_gives_back_color_numpy_and_torch():
    b = synthetic_buffers()
    x = make_network_inputs(b, EPS)
    c = rebuild_color(x["diffuse_t"], x["specular_t"], x["albedo"], EPS)
    np.testing.assert_allclose(c, b["color"], rtol=1e-5, atol=1e-6)
    t = {k: torch.from_numpy(x[k]) for k in ("diffuse_t", "specular_t", "albedo")}
    ct = rebuild_color(t["diffuse_t"], t["specular_t"], t["albedo"], EPS)
    assert isinstance(ct, torch.Tensor)
    np.testing.assert_allclose(ct.numpy(), b["color"], rtol=1e-5, atol=1e-6)


def test_transforms_match_bako():
    b = synthetic_buffers()
    np.testing.assert_allclose(
        transform_diffuse(b["diffuse"], b["albedo"], EPS), b["diffuse"] / (b["albedo"] + EPS)
    )
    np.testing.assert_allclose(
        transform_specular(b["specular"]), np.log(1 + b["specular"].astype(float)), rtol=1e-6
    )


def _mc_var(fn, mu, sigma, n=400_000, seed=1):
    """Variance of fn(s) for s ~ N(mu, sigma^2), per value of mu (brute force)."""
    s = np.random.default_rng(seed).normal(mu[:, None], sigma, size=(len(mu), n))
    return fn(s).var(axis=1)


def test_specular_variance_matches_monte_carlo_and_catches_known_bugs():
    mu, sigma = np.array([0.05, 0.5, 2.0, 10.0]), 0.01
    var = np.full((4, 1, 1), sigma**2)  # (H=4, W=1, C=1) variance of the pixel mean
    spec = np.repeat(mu[:, None, None], 3, axis=2)  # grey: channel mean = mu
    mc = _mc_var(np.log1p, mu, sigma)
    ours = transform_specular_variance(var, spec)[:, 0, 0]
    np.testing.assert_allclose(ours, mc, rtol=0.02)
    wrong_log = (var / (1 + np.log1p(spec).mean(-1, keepdims=True)) ** 2)[:, 0, 0]
    wrong_eps = (var / (spec.mean(-1, keepdims=True) + 1e-5) ** 2)[:, 0, 0]
    for wrong in (wrong_log, wrong_eps):
        assert not np.allclose(wrong, mc, rtol=0.02)


def test_diffuse_variance_matches_monte_carlo():
    mu, sigma = np.array([0.1, 1.0, 4.0]), 0.02
    albedo = np.array([0.02, 0.3, 0.8])
    a = np.repeat(albedo[:, None, None], 3, axis=2)
    ours = transform_diffuse_variance(np.full((3, 1, 1), sigma**2), a, EPS)[:, 0, 0]
    mc = np.array(
        [_mc_var(lambda s, al=al: s / (al + EPS), mu[i : i + 1], sigma)[0] for i, al in enumerate(albedo)]
    )
    np.testing.assert_allclose(ours, mc, rtol=0.02)


def test_normalize_depth():
    d = np.arange(6, dtype=np.float32).reshape(2, 3, 1)
    nd, nv = normalize_depth(d, np.ones_like(d))
    np.testing.assert_allclose(nd, d / 5)
    np.testing.assert_allclose(nv, 1 / 25)
    zd, zv = normalize_depth(np.zeros_like(d), np.ones_like(d))
    assert not zd.any() and not zv.any()


def test_gradients_non_square_against_slow_reference():
    x = np.random.default_rng(0).random((13, 21, 2))
    g = image_gradients(x)
    assert g.shape == (13, 21, 4)
    ref = np.zeros_like(g)
    for i in range(13):
        for j in range(21):
            if j > 0:
                ref[i, j, :2] = x[i, j] - x[i, j - 1]
            if i > 0:
                ref[i, j, 2:] = x[i, j] - x[i - 1, j]
    np.testing.assert_array_equal(g, ref)


def test_network_inputs_hold_every_candidate_feature_in_the_documented_order():
    b = synthetic_buffers()
    x = make_network_inputs(b, EPS)
    assert len(CANDIDATE_CHANNELS) == 38 and len(set(CANDIDATE_CHANNELS)) == 38
    for branch in ("diffuse", "specular"):
        a = x[f"{branch}_in"]
        assert a.shape == (13, 21, 38) and a.dtype == np.float32
        np.testing.assert_array_equal(a[..., :3], x[f"{branch}_t"])
        np.testing.assert_array_equal(a[..., 4:10], image_gradients(x[f"{branch}_t"]))
    ch = {n: i for i, n in enumerate(CANDIDATE_CHANNELS)}

    def channels(name, count=1):
        return x["diffuse_in"][..., ch[name] : ch[name] + count]

    np.testing.assert_allclose(channels("depth")[..., 0], b["depth"][..., 0] / b["depth"].max(), rtol=1e-6)
    np.testing.assert_allclose(
        x["specular_in"][..., ch["color_var"]],
        (b["specularVariance"] / (1 + b["specular"].mean(-1, keepdims=True)) ** 2)[..., 0],
        rtol=1e-6,
    )
    np.testing.assert_array_equal(channels("normal_x", 3), b["normal"])
    np.testing.assert_array_equal(channels("normal_var"), b["normalVariance"])
    np.testing.assert_array_equal(channels("normal_dx_x", 6), image_gradients(b["normal"]))
    np.testing.assert_array_equal(channels("albedo_r", 3), b["albedo"])
    np.testing.assert_array_equal(channels("albedo_var"), b["albedoVariance"])
    np.testing.assert_array_equal(channels("albedo_dx_r", 6), image_gradients(b["albedo"]))
    np.testing.assert_array_equal(channels("visibility"), b["visibility"])
    np.testing.assert_array_equal(channels("visibility_var"), b["visibilityVariance"])
    np.testing.assert_array_equal(channels("visibility_dx_v", 2), image_gradients(b["visibility"]))
    np.testing.assert_array_equal(x["diffuse_in"][..., 10:], x["specular_in"][..., 10:])  # shared features
    bad = dict(b)
    bad["normal"] = b["normal"][:, :-1]
    with pytest.raises(DataError, match="normal"):
        make_network_inputs(bad, EPS)
    bad = {k: v for k, v in b.items() if k != "visibility"}
    with pytest.raises(DataError, match="'visibility' is missing"):
        make_network_inputs(bad, EPS)


def test_targets_use_reference_specular_and_noisy_albedo():
    noisy, ref = synthetic_buffers(seed=1), synthetic_buffers(seed=2)
    assert not np.allclose(noisy["specular"], ref["specular"])
    x = make_network_inputs(noisy, EPS)
    t = make_targets(ref, x["albedo"], EPS)
    np.testing.assert_allclose(t["specular_target"], np.log1p(ref["specular"]), rtol=1e-6)
    np.testing.assert_allclose(t["diffuse_target"], ref["diffuse"] / (noisy["albedo"] + EPS), rtol=1e-6)
    back = rebuild_color(t["diffuse_target"], t["specular_target"], x["albedo"], EPS)
    np.testing.assert_allclose(back, ref["color"], rtol=1e-5, atol=1e-6)


def test_whitening_stats_streaming_and_json(tmp_path):
    rng = np.random.default_rng(0)
    parts = [1e3 + rng.normal(size=(n, 5, 7, 4)) * [1, 2, 3, 0] for n in (1, 3, 2)]
    stats = compute_whitening_stats(iter(parts), std_eps=1e-3)
    flat = np.concatenate(parts).reshape(-1, 4)
    np.testing.assert_allclose(stats.mean, flat.mean(0), rtol=1e-12)
    np.testing.assert_allclose(stats.std[:3], flat.std(0)[:3], rtol=1e-9)
    assert stats.std[3] == 1e-3  # constant channel: floored
    w = whiten(parts[0].astype(np.float32), stats)
    assert w.dtype == np.float32 and np.abs(w[..., :3].mean()) < 1
    wt = whiten(torch.from_numpy(parts[0]).permute(0, 3, 1, 2), stats, channel_axis=1)
    np.testing.assert_allclose(wt.permute(0, 2, 3, 1).numpy(), whiten(parts[0], stats), rtol=1e-12)
    save_whitening_stats(tmp_path / "w.json", {"diffuse_in": stats})
    back = load_whitening_stats(tmp_path / "w.json")["diffuse_in"]
    np.testing.assert_array_equal(back.mean, stats.mean)
    np.testing.assert_array_equal(back.std, stats.std)


# --- mutation-testing additions (scripts/mutation.sh) ----------------------------------------------------


def test_rebuild_color_is_differentiable_for_torch_outputs():
    # Training calls it on network outputs: it must stay in torch (numpy would drop the graph).
    d = torch.tensor([[[0.5, 1.0, 2.0]]], dtype=torch.float64, requires_grad=True)
    s = torch.tensor([[[0.1, 0.0, 1.0]]], dtype=torch.float64, requires_grad=True)
    albedo = torch.tensor([[[0.2, 0.4, 0.8]]], dtype=torch.float64)
    c = rebuild_color(d, s, albedo, EPS)
    c.sum().backward()
    np.testing.assert_allclose(d.grad.numpy(), albedo.numpy() + EPS)  # dc/dd' = albedo + eps
    np.testing.assert_allclose(s.grad.numpy(), np.exp(s.detach().numpy()))  # dc/ds' = exp(s')


def test_normalize_depth_below_one_and_degenerate_inputs():
    d = np.array([[[0.1], [0.5]]], dtype=np.float32)  # max 0.5 < 1: still scaled up to 1
    nd, nv = normalize_depth(d, np.full_like(d, 0.01))
    np.testing.assert_allclose(nd, d / 0.5)
    np.testing.assert_allclose(nv, 0.01 / 0.25)
    zd, zv = normalize_depth(np.zeros((2, 3, 1), np.float32), np.ones((2, 3, 1), np.float32))
    assert zd.shape == zv.shape == (2, 3, 1) and zd.dtype == zv.dtype == np.float32
    empty = np.zeros((0, 3, 1), np.float32)
    ed, ev = normalize_depth(empty, empty)  # no max() of an empty array
    assert ed.shape == ev.shape == (0, 3, 1)


def test_network_inputs_return_the_baseline_guides_and_name_the_image():
    b = synthetic_buffers()
    x = make_network_inputs(b, EPS)
    np.testing.assert_array_equal(x["normal"], b["normal"])
    np.testing.assert_allclose(x["depth"], b["depth"] / b["depth"].max(), rtol=1e-6)
    bad = dict(b)
    bad["depth"] = b["depth"][..., 0]  # (H, W): a missing channel axis is a DataError, not an IndexError
    with pytest.raises(DataError, match="noisy image: buffer 'depth'"):
        make_network_inputs(bad, EPS)


def test_targets_are_float32_and_name_the_reference():
    noisy, ref = synthetic_buffers(seed=1), synthetic_buffers(seed=2)
    ref64 = {k: v.astype(np.float64) for k, v in ref.items()}
    t = make_targets(ref64, noisy["albedo"], EPS)
    assert t["diffuse_target"].dtype == t["specular_target"].dtype == np.float32
    with pytest.raises(DataError, match="reference image: buffer 'specular'"):
        make_targets({"diffuse": ref["diffuse"]}, noisy["albedo"], EPS)


def test_whitening_stats_accumulate_in_float64_and_skip_nothing():
    rng = np.random.default_rng(3)
    # float32 input with a large offset: float32 accumulation would be off by ~1e-4 relative
    parts = [(1e4 + rng.normal(size=(n, 2))).astype(np.float32) for n in (0, 1, 999, 1)]
    stats = compute_whitening_stats(iter(parts), std_eps=1e-6)
    flat = np.concatenate(parts).astype(
        np.float64
    )  # the single-row parts count too; the empty one is skipped
    np.testing.assert_allclose(stats.mean, flat.mean(0), rtol=1e-13)
    np.testing.assert_allclose(stats.std, flat.std(0), rtol=1e-9)


def test_float64_buffers_give_the_same_bits_as_float32_ones():
    # Buffers are cast to float32 first: where they come from (EXR half/float, a float64 array) does not
    # change a single value of the network inputs or targets.
    b32 = synthetic_buffers()
    b64 = {k: v.astype(np.float64) for k, v in b32.items()}
    x32, x64 = make_network_inputs(b32, EPS), make_network_inputs(b64, EPS)
    for k in x32:
        np.testing.assert_array_equal(x64[k], x32[k])
    t32, t64 = make_targets(b32, x32["albedo"], EPS), make_targets(b64, x32["albedo"], EPS)
    for k in t32:
        np.testing.assert_array_equal(t64[k], t32[k])


# Surviving mutants (bash scripts/mutation.sh kpcn), each equivalent for the reason given:
# - normalize_depth `else 0.0` -> `else 1.0`: only reached for an empty depth, where depth / 1 is the same
#   empty array as zeros_like (test_normalize_depth_below_one_and_degenerate_inputs).
# - make_network_inputs / whiten `astype(..., copy=False)` -> copy=True/None/default: copying or not
#   changes no value.
# - WhiteningStats.from_dict dtype=float64 -> None/default: JSON numbers load as Python floats, which
#   numpy stores as float64 anyway.
# - RunningMoments.__init__ n = 0 -> None/1, m2 = None -> "": overwritten by the first non-empty update
#   (`self.mean is None` decides), and finalize refuses to run before one.
# - RunningMoments.update reshape(-1, C) -> reshape(-2, C) and whiten shape[axis] = -1 -> -2: numpy
#   treats any negative size as "infer this dimension".


def test_the_thesis_specular_variance_is_an_option_for_replication():
    """Default: the first-order variance (matches Monte Carlo above). `thesis`: var / (log1p(s) + 1e-5)^2,
    the seed thesis's Sec. 4.3 formula as its author's code has it, which is far off for small and large s."""
    mu, sigma = np.array([0.05, 0.5, 2.0, 10.0]), 0.01
    var = np.full((4, 1, 1), sigma**2)
    spec = np.repeat(mu[:, None, None], 3, axis=2)
    thesis = transform_specular_variance_thesis(var, spec)[:, 0, 0]
    np.testing.assert_allclose(thesis, sigma**2 / (np.log1p(mu) + 1e-5) ** 2, rtol=1e-12)
    ratio = thesis / _mc_var(np.log1p, mu, sigma)
    assert ratio.max() > 100 and not np.allclose(ratio, 1, rtol=0.1)  # why it is not the default
    b = synthetic_buffers()
    x = make_network_inputs(b, EPS, specular_variance="thesis")
    channel = list(CANDIDATE_CHANNELS).index("color_var")
    np.testing.assert_allclose(
        x["specular_in"][..., channel],
        transform_specular_variance_thesis(b["specularVariance"], b["specular"])[..., 0],
    )
    np.testing.assert_array_equal(
        x["diffuse_in"], make_network_inputs(b, EPS)["diffuse_in"]
    )  # diffuse unchanged
    with pytest.raises(ConfigError) as excinfo:
        make_network_inputs(b, EPS, specular_variance="exact")
    one_line_error(excinfo, "dataset.preprocess.specular_variance='exact'", "'thesis'")


def test_log_modulus_is_odd_inverts_and_is_log1p_for_non_negative_values():
    x = np.concatenate([-np.logspace(-8, 6, 50), [0.0], np.logspace(-8, 6, 50)])
    y = log_modulus(x)
    np.testing.assert_allclose(y, np.sign(x) * np.log1p(np.abs(x)), rtol=1e-15)
    np.testing.assert_array_equal(log_modulus(-x), -y)  # odd
    np.testing.assert_array_equal(y[x >= 0], np.log1p(x[x >= 0]))
    np.testing.assert_allclose(inverse_log_modulus(y), x, rtol=1e-12)
    x32 = x.astype(np.float32)
    assert log_modulus(x32).dtype == inverse_log_modulus(log_modulus(x32)).dtype == np.float32
    t = torch.from_numpy(x)
    np.testing.assert_allclose(log_modulus(t).numpy(), y, rtol=1e-15)  # torch's log1p: 1 ulp
    np.testing.assert_allclose(inverse_log_modulus(log_modulus(t)).numpy(), x, rtol=1e-12)


def test_log_modulus_has_slope_one_at_zero_also_under_autograd():
    h = 1e-7
    assert (log_modulus(h) - log_modulus(-h)) / (2 * h) == pytest.approx(1.0, rel=1e-6)
    # sign(x) * log1p(|x|) would give autograd slope 0 at 0; large |x| of the other sign: no NaN
    x = torch.tensor([0.0, -3.0, 5.0, 1e30, -1e30], dtype=torch.float64, requires_grad=True)
    log_modulus(x).sum().backward()
    np.testing.assert_allclose(x.grad.numpy(), 1 / (1 + np.abs(x.detach().numpy())), rtol=1e-12)
    y = torch.tensor([0.0, -2.0, 700.0, -700.0], dtype=torch.float64, requires_grad=True)
    inverse_log_modulus(y).sum().backward()
    np.testing.assert_allclose(y.grad.numpy(), np.exp(np.abs(y.detach().numpy())), rtol=1e-12)


def test_log_modulus_variance_matches_monte_carlo():
    """First-order Var[log_modulus(mean)] = Var / (1 + |x|)^2, also for negative values and at 0."""
    mu, sigma = np.array([-10.0, -0.5, 0.0, 0.05, 2.0, 10.0]), 0.01
    var = np.full((6, 1, 1), sigma**2)
    x = np.repeat(mu[:, None, None], 3, axis=2)  # grey: channel mean of |x| = |mu|
    mc = _mc_var(log_modulus, mu, sigma)
    ours = log_modulus_variance(var, x)[:, 0, 0]
    np.testing.assert_allclose(ours, mc, rtol=0.02)
    wrong_log = (var / (1 + np.abs(log_modulus(x)).mean(-1, keepdims=True)) ** 2)[:, 0, 0]
    assert not np.allclose(wrong_log, mc, rtol=0.02)  # the derivative at the transformed value
    spec = 5 * np.random.default_rng(0).random((4, 5, 3))  # non-negative: the specular delta transform
    v = np.random.default_rng(1).random((4, 5, 1))
    np.testing.assert_allclose(log_modulus_variance(v, spec), transform_specular_variance(v, spec))
