"""NeRF math against independent references: Monte Carlo estimates (IPE, frustum moments, IDE under a vMF
distribution, SH orthonormality), closed forms (volume rendering, scipy's spherical harmonics) and
histograms (inverse-CDF sampling). Monte Carlo tolerances are a few standard errors, estimated from the
same samples; every random draw is seeded."""

import math

import pytest
import torch
from scipy.special import ive, sph_harm_y

from src.models.nerf.directional import (
    complex_sph_harm,
    dir_enc,
    ide_degrees,
    ide_dim,
    integrated_dir_enc,
    l2_normalize,
    real_sph_harm,
    reflect,
)
from src.models.nerf.encodings import (
    cast_rays,
    conical_frustum_to_gaussian,
    expected_sin,
    integrated_pos_enc,
    pos_enc,
)
from src.models.nerf.sampling import blur_weights, resample_tdist, sample_pdf, stratified_samples
from src.models.nerf.volume import compute_alpha_weights, volumetric_rendering

F64 = torch.float64
#: Standard errors allowed between a Monte Carlo estimate and the exact value.
Z = 5.0


def gen(seed: int = 0) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


def mc_mean_and_stderr(samples: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean over dim 0 and its standard error."""
    return samples.mean(dim=0), samples.std(dim=0) / math.sqrt(samples.shape[0])


def assert_within(actual: torch.Tensor, expected: torch.Tensor, tol: torch.Tensor | float) -> None:
    err = (actual - expected).abs()
    excess = err - tol
    assert bool((excess <= 0).all()), (
        f"max error {err.max().item():.3g}, worst excess {excess.max().item():.3g}"
    )


def unit_vectors(n: int, g: torch.Generator) -> torch.Tensor:
    return l2_normalize(torch.randn(n, 3, generator=g, dtype=F64))


# --- positional encodings --------------------------------------------------------------------------------


def test_pos_enc_layout():
    x = torch.tensor([[0.3, -1.2, 2.0]], dtype=F64)
    enc = pos_enc(x, 0, 3, append_identity=True)
    assert enc.shape == (1, 3 + 3 * 2 * 3)
    scaled = torch.cat([x * 1, x * 2, x * 4], dim=-1)  # degree-major, coordinate-minor
    expected = torch.cat([x, torch.sin(scaled), torch.cos(scaled)], dim=-1)
    assert_within(enc, expected, 1e-12)
    assert pos_enc(x, 0, 3, append_identity=False).shape == (1, 18)
    assert pos_enc(x, 2, 5, append_identity=False)[0, 0] == pytest.approx(math.sin(0.3 * 4))


def test_expected_sin_closed_form():
    mean, var = torch.tensor([0.7], dtype=F64), torch.tensor([0.4], dtype=F64)
    assert expected_sin(mean, var).item() == pytest.approx(math.exp(-0.2) * math.sin(0.7))


def test_ipe_matches_monte_carlo():
    """IPE = E[PE(x)] for x ~ N(mean, diag(var)) (mip-NeRF Eq. 14-16), checked by sampling x."""
    g = gen(1)
    min_deg, max_deg, n = 0, 5, 200_000
    mean = torch.randn(4, 3, generator=g, dtype=F64)
    var = 0.001 + 0.05 * torch.rand(4, 3, generator=g, dtype=F64)
    ipe = integrated_pos_enc(mean, var, min_deg, max_deg)
    assert ipe.shape == (4, 3 * 2 * (max_deg - min_deg))
    for b in range(4):
        x = mean[b] + var[b].sqrt() * torch.randn(n, 3, generator=g, dtype=F64)
        est, stderr = mc_mean_and_stderr(pos_enc(x, min_deg, max_deg, append_identity=False))
        assert_within(ipe[b], est, Z * stderr + 1e-9)


def test_ipe_with_zero_variance_is_pos_enc():
    x = torch.randn(5, 7, 3, generator=gen(2), dtype=F64)
    ipe = integrated_pos_enc(x, torch.zeros_like(x), 0, 16)
    assert_within(ipe, pos_enc(x, 0, 16, append_identity=False), 1e-12)


# --- conical frusta -----------------------------------------------------------------------------------


def sample_frustum(d, t0, t1, radius, n, g):
    """Points uniform by volume in {t d + r u : t in [t0, t1], u _|_ d, |r| <= t * radius}: t has density
    proportional to t^2 (cross-section area), the offset is uniform in the disk of radius t * radius."""
    u = torch.rand(n, generator=g, dtype=F64)
    t = (t0**3 + u * (t1**3 - t0**3)) ** (1 / 3)
    rho = t * radius * torch.rand(n, generator=g, dtype=F64).sqrt()
    phi = 2 * math.pi * torch.rand(n, generator=g, dtype=F64)
    e1 = l2_normalize(torch.linalg.cross(d, torch.tensor([1.0, 0.0, 0.0], dtype=F64)))
    e2 = torch.linalg.cross(l2_normalize(d), e1)
    offset = rho[:, None] * (phi.cos()[:, None] * e1 + phi.sin()[:, None] * e2)
    return t[:, None] * d + offset


def paper_frustum_moments(t0, t1, radius):
    """mip-NeRF Eq. 7 in its original (unstable, but exact in float64 here) form."""
    mu_t = 3 * (t1**4 - t0**4) / (4 * (t1**3 - t0**3))
    var_t = 3 * (t1**5 - t0**5) / (5 * (t1**3 - t0**3)) - mu_t**2
    var_r = radius**2 * 3 * (t1**5 - t0**5) / (20 * (t1**3 - t0**3))
    return mu_t, var_t, var_r


@pytest.mark.parametrize(("t0", "t1"), [(1.5, 2.5), (2.0, 2.05), (0.1, 4.0)])
def test_frustum_gaussian_matches_monte_carlo(t0, t1):
    g = gen(3)
    d = torch.tensor([0.3, -0.2, -1.0], dtype=F64)  # not unit length: the formulas scale with ||d||
    origin = torch.tensor([0.5, 1.0, -2.0], dtype=F64)
    radius = 0.2
    tdist = torch.tensor([[t0, t1]], dtype=F64)
    radii = torch.tensor([[radius]], dtype=F64)
    mean, cov = cast_rays(tdist, origin[None], d[None], radii, diag=False)
    mean_d, cov_d = cast_rays(tdist, origin[None], d[None], radii, diag=True)
    mean, cov, mean_d, cov_d = mean[0, 0], cov[0, 0], mean_d[0, 0], cov_d[0, 0]
    assert_within(mean_d, mean, 1e-12)
    assert_within(cov_d, torch.diagonal(cov), 1e-12)

    # Exact moments (the paper's form, fine in float64) and the stable form agree.
    mu_t, var_t, var_r = paper_frustum_moments(t0, t1, radius)
    d_outer = torch.outer(d, d)
    exact_cov = var_t * d_outer + var_r * (torch.eye(3, dtype=F64) - d_outer / (d @ d))
    assert_within(mean, origin + mu_t * d, 1e-9)
    assert_within(cov, exact_cov, 1e-9)

    x = origin + sample_frustum(d, t0, t1, radius, 400_000, g)
    est_mean, se_mean = mc_mean_and_stderr(x)
    assert_within(mean, est_mean, Z * se_mean)
    centred = x - mean  # the exact mean: the outer products are then unbiased estimates of cov
    products = centred[:, :, None] * centred[:, None, :]
    est_cov, se_cov = mc_mean_and_stderr(products)
    assert_within(cov, est_cov, Z * se_cov + 1e-12)


def test_conical_frustum_stable_for_tiny_intervals():
    """The midpoint/half-width form stays accurate where t1^3 - t0^3 cancels in float32."""
    d = torch.tensor([[0.0, 0.0, -1.0]])
    t0, t1 = torch.tensor([[100.0]]), torch.tensor([[100.01]])
    _, cov = conical_frustum_to_gaussian(d, t0, t1, torch.tensor([[0.01]]), diag=True)
    assert cov[0, 0, 2].item() == pytest.approx(0.01**2 / 12, rel=1e-3)  # var_t -> hw^2 / 3
    assert cov[0, 0, 0].item() == pytest.approx(0.01**2 * 100.005**2 / 4, rel=1e-3)  # r_var -> R^2 mu^2 / 4


# --- spherical harmonics and the IDE ------------------------------------------------------------------------


def test_sph_harm_matches_scipy_and_closed_forms():
    g = gen(4)
    xyz = unit_vectors(2000, g)
    lms = [(l, m) for l in range(17) for m in range(l + 1)]  # noqa: E741
    re, im = complex_sph_harm(xyz, lms)
    theta, phi = torch.acos(xyz[:, 2]).numpy(), torch.atan2(xyz[:, 1], xyz[:, 0]).numpy()
    for f, (l, m) in enumerate(lms):  # noqa: E741
        ref = sph_harm_y(l, m, theta, phi)  # scipy: orthonormal, Condon-Shortley phase
        assert_within(re[:, f], torch.from_numpy(ref.real), 1e-9)
        assert_within(im[:, f], torch.from_numpy(ref.imag), 1e-9)
    x, y, z = xyz.unbind(-1)
    assert_within(re[:, 1], math.sqrt(3 / (4 * math.pi)) * z, 1e-12)  # Y_1^0
    assert_within(re[:, 2], -math.sqrt(3 / (8 * math.pi)) * x, 1e-12)  # Re Y_1^1
    assert_within(im[:, 5], 0.25 * math.sqrt(15 / (2 * math.pi)) * 2 * x * y, 1e-12)  # Im Y_2^2


def gram_by_monte_carlo(features: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """4 pi E[f_i f_j] for directions uniform on the sphere, and its standard error: the second moments
    of the products come from one matmul of the squared features."""
    n = features.shape[0]
    gram = 4 * math.pi * features.T @ features / n
    second = (4 * math.pi) ** 2 * (features**2).T @ (features**2) / n
    return gram, torch.sqrt(torch.clamp(second - gram**2, min=0.0) / n)


def test_real_sph_harm_orthonormal():
    feats = real_sph_harm(unit_vectors(200_000, gen(5)), l_max=4)
    assert feats.shape[-1] == 25
    gram, stderr = gram_by_monte_carlo(feats)
    assert_within(gram, torch.eye(25, dtype=F64), Z * stderr + 1e-9)


def test_ide_features_orthogonal_and_normalised():
    """The IDE's features at kappa_inv = 0: Re Y_l^m (norm 1 for m = 0, 1/2 otherwise), Im Y_l^m (norm
    1/2, identically zero for m = 0), mutually orthogonal."""
    feats = dir_enc(unit_vectors(100_000, gen(6)), 5)
    assert feats.shape[-1] == ide_dim(5) == 72
    ms = torch.tensor([m for _, m in ide_degrees(5)] * 2)
    imag = torch.arange(72) >= 36
    zero = imag & (ms == 0)
    assert bool((feats[:, zero] == 0).all())
    norms = torch.where(ms == 0, 1.0, 0.5).to(F64)[~zero]
    gram, stderr = gram_by_monte_carlo(feats[:, ~zero])
    assert_within(gram, torch.diag(norms), Z * stderr + 1e-9)


def sample_vmf(mu: torch.Tensor, kappa: float, n: int, g: torch.Generator) -> torch.Tensor:
    """Exact vMF samples on S^2: w = cos(angle to mu) = 1 + log(u + (1 - u) e^{-2 kappa}) / kappa, the
    azimuth uniform."""
    u = torch.rand(n, generator=g, dtype=F64)
    w = 1 + torch.log(u + (1 - u) * math.exp(-2 * kappa)) / kappa
    phi = 2 * math.pi * torch.rand(n, generator=g, dtype=F64)
    e1 = l2_normalize(torch.linalg.cross(mu, torch.tensor([0.3, 1.0, 0.2], dtype=F64)))
    e2 = torch.linalg.cross(mu, e1)
    s = torch.sqrt(torch.clamp(1 - w**2, min=0.0))
    return w[:, None] * mu + s[:, None] * (phi.cos()[:, None] * e1 + phi.sin()[:, None] * e2)


@pytest.mark.parametrize("kappa", [2.0, 10.0, 50.0, 500.0])
def test_ide_matches_vmf_monte_carlo(kappa):
    """E_{omega ~ vMF(mu, kappa)}[Y_l^m(omega)] = A_l(kappa) Y_l^m(mu) exactly (Funk-Hecke, A_l the
    ratio of modified Bessel functions I_{l+1/2} / I_{1/2}); Ref-NeRF's IDE uses exp(-l(l+1) / 2kappa)
    for A_l. The Monte Carlo mean must match the exact form within its error, and the IDE within its
    error plus the approximation's (which is small once kappa >= 10)."""
    g = gen(7)
    mu = l2_normalize(torch.tensor([0.4, -0.5, 0.75], dtype=F64))
    samples = sample_vmf(mu, kappa, 200_000, g)
    assert_within((samples @ mu).mean(), 1 / math.tanh(kappa) - 1 / kappa, 1e-2)  # E[w] = A_1(kappa)
    est, stderr = mc_mean_and_stderr(dir_enc(samples, 5))
    plain = dir_enc(mu[None], 5)[0]
    degrees = [deg for deg, _ in ide_degrees(5)] * 2
    exact_att = torch.tensor([ive(deg + 0.5, kappa) / ive(0.5, kappa) for deg in degrees], dtype=F64)
    assert_within(exact_att * plain, est, Z * stderr + 1e-9)

    ide = integrated_dir_enc(mu[None], torch.tensor([[1 / kappa]], dtype=F64), 5)[0]
    approx_err = ((ide - exact_att * plain).abs()).max().item()
    if kappa >= 10:
        assert approx_err < 0.02
    assert_within(ide, est, Z * stderr + approx_err + 1e-9)


def test_dir_enc_is_ide_at_zero_roughness():
    xyz = unit_vectors(100, gen(8)).float()
    assert_within(dir_enc(xyz, 5), integrated_dir_enc(xyz, torch.zeros(100, 1), 5), 0.0)
    assert dir_enc(xyz, 3).shape == (100, 2 * (2 + 3 + 5))


def test_ide_float32_accurate():
    xyz = unit_vectors(10_000, gen(9))
    assert_within(dir_enc(xyz.float(), 5).double(), dir_enc(xyz, 5), 1e-4)


def test_reflect():
    g = gen(10)
    v, n = unit_vectors(50, g), unit_vectors(50, g)
    r = reflect(v, n)
    assert_within(r.norm(dim=-1), torch.ones(50, dtype=F64), 1e-12)
    assert_within((r * n).sum(-1), (v * n).sum(-1), 1e-12)  # same angle to the normal
    assert_within(reflect(r, n), v, 1e-12)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    assert_within(reflect(torch.tensor([1.0, 0.0, 1.0], dtype=F64), z), torch.tensor([-1.0, 0.0, 1.0]), 1e-12)


# --- volume rendering --------------------------------------------------------------------------------------


def test_alpha_weights_opaque_slab():
    tdist = torch.linspace(2.0, 6.0, 9, dtype=F64)[None]
    density = torch.zeros(1, 8, dtype=F64)
    density[0, 3] = 1e4
    dirs = torch.tensor([[0.0, 0.6, -0.8]], dtype=F64)
    weights, alpha, trans = compute_alpha_weights(density, tdist, dirs)
    expected = torch.zeros(1, 8, dtype=F64)
    expected[0, 3] = 1.0
    assert_within(weights, expected, 1e-12)
    assert_within(trans[0, 4:], torch.zeros(4, dtype=F64), 1e-12)
    assert_within(alpha[0, :3], torch.zeros(3, dtype=F64), 0.0)
    rgb = torch.rand(1, 8, 3, generator=gen(11), dtype=F64)
    out = volumetric_rendering(rgb, weights, tdist, torch.ones(3, dtype=F64))
    assert_within(out["rgb"], rgb[:, 3], 1e-12)
    assert out["acc"].item() == pytest.approx(1.0)
    assert out["depth"].item() == pytest.approx(3.75)  # the interval's midpoint


def test_alpha_weights_empty_space():
    tdist = torch.linspace(1.0, 3.0, 5)[None].expand(2, 5)
    weights, _, trans = compute_alpha_weights(torch.zeros(2, 4), tdist, torch.ones(2, 3))
    assert bool((weights == 0).all()) and bool((trans == 1).all())
    background = torch.tensor([0.2, 0.5, 1.0])
    out = volumetric_rendering(torch.rand(2, 4, 3), weights, tdist, background)
    assert bool((out["acc"] == 0).all())
    assert_within(out["rgb"], background.expand(2, 3), 0.0)
    assert_within(out["depth"], torch.ones(2), 0.0)  # clipped to t_0


def test_alpha_weights_constant_density_closed_form():
    """acc = 1 - exp(-sigma L) with L the metric length ||d|| (far - near), and the transmittance at
    every endpoint is exp(-sigma * distance travelled), whatever the (uneven) intervals."""
    sigma, near, far = 0.7, 2.0, 5.0
    dirs = torch.tensor([[1.0, 2.0, -2.0]], dtype=F64)  # ||d|| = 3
    tdist = torch.sort(near + (far - near) * torch.rand(1, 31, generator=gen(12), dtype=F64)).values
    tdist = torch.cat([torch.tensor([[near]], dtype=F64), tdist, torch.tensor([[far]], dtype=F64)], dim=-1)
    weights, _, trans = compute_alpha_weights(torch.full((1, 32), sigma, dtype=F64), tdist, dirs)
    assert weights.sum().item() == pytest.approx(1 - math.exp(-sigma * 3 * (far - near)), rel=1e-12)
    assert_within(trans, torch.exp(-sigma * 3 * (tdist[:, :-1] - near)), 1e-12)


# --- sampling --------------------------------------------------------------------------------------------


def test_stratified_samples():
    near, far = torch.full((500, 1), 2.0), torch.full((500, 1), 6.0)
    det = stratified_samples(near, far, 16, randomized=False)
    assert det.shape == (500, 17)
    assert_within(det[0], torch.linspace(2.0, 6.0, 17), 1e-6)
    rnd = stratified_samples(near, far, 16, randomized=True, generator=gen(13))
    assert bool((rnd[:, 1:] >= rnd[:, :-1]).all())
    assert bool((rnd >= 2.0).all() and (rnd <= 6.0).all())
    assert rnd.mean().item() == pytest.approx(4.0, abs=0.02)  # unbiased jitter
    lin = stratified_samples(near, far, 4, randomized=False, lindisp=True)
    assert_within(1 / lin[0], torch.linspace(0.5, 1 / 6.0, 5), 1e-6)


def test_sample_pdf_follows_piecewise_constant_pdf():
    """Histogram test: bin counts proportional to the weights (an empty bin gets nothing), uniform
    inside a bin."""
    bins = torch.tensor([0.0, 1.0, 1.5, 3.0, 3.2, 5.0])
    weights = torch.tensor([0.1, 0.4, 0.0, 0.3, 0.2])
    n_rays, n_samples = 2000, 64
    samples = sample_pdf(
        bins.expand(n_rays, -1), weights.expand(n_rays, -1), n_samples, randomized=True, generator=gen(14)
    )
    assert samples.shape == (n_rays, n_samples)
    assert bool((samples[:, 1:] >= samples[:, :-1]).all())
    flat = samples.flatten()
    counts = torch.histogram(flat, bins=bins).hist
    expected = weights / weights.sum() * flat.numel()
    assert_within(counts, expected, Z * expected.sqrt() + 1)
    assert not bool(((flat > 1.5) & (flat < 3.0)).any())  # the empty bin's interior gets nothing
    sub = flat[(flat >= 1.0) & (flat < 1.5)]
    sub_counts = torch.histogram(sub, bins=torch.linspace(1.0, 1.5, 6)).hist
    assert_within(sub_counts, torch.full((5,), sub.numel() / 5), Z * math.sqrt(sub.numel() / 5))


def test_sample_pdf_deterministic_and_empty_rays():
    bins = torch.linspace(0.0, 1.0, 5)[None]
    uniform = sample_pdf(bins, torch.ones(1, 4), 11, randomized=False)
    assert_within(uniform[0], torch.linspace(0.0, 1 - 1e-5, 11), 1e-5)
    empty = sample_pdf(bins, torch.zeros(1, 4), 11, randomized=False)  # padded to uniform, no NaN
    assert_within(empty, uniform, 1e-5)


def test_blur_weights():
    # Edge-replicated [0, 0, 1, 0, 0, .5, .5] -> 2-tap max [0, 1, 1, 0, .5, .5] -> 2-tap mean.
    w = torch.tensor([[0.0, 1.0, 0.0, 0.0, 0.5]])
    assert_within(blur_weights(w, 0.01), torch.tensor([[0.5, 1.0, 0.5, 0.25, 0.5]]) + 0.01, 1e-7)


def test_resample_tdist_sorted():
    g = gen(15)
    near, far = torch.full((64, 1), 2.0), torch.full((64, 1), 6.0)
    tdist = stratified_samples(near, far, 32, randomized=True, generator=g)
    weights = torch.rand(64, 32, generator=g) ** 4
    weights.requires_grad_(True)
    mip = resample_tdist(tdist, weights, 48, randomized=True, blur_padding=0.01, generator=g)
    nerf = resample_tdist(tdist, weights, 48, randomized=True, blur_padding=None, generator=g)
    assert mip.shape == (64, 49) and nerf.shape == (64, 33 + 48)
    for t in (mip, nerf):
        assert not t.requires_grad
        assert bool((t[:, 1:] >= t[:, :-1]).all())
        assert bool((t >= tdist[:, :1]).all() and (t <= tdist[:, -1:]).all())
    # The merged NeRF set keeps every coarse endpoint.
    assert bool(torch.isin(tdist, nerf).all())


# --- mutation-testing additions (scripts/mutation.sh) ----------------------------------------------------
# Every function here is batched over leading dimensions and keeps the dtype/device of its inputs; the
# three tests below check both for all of them at once (a `dim=-1` written as `dim=1`, a reduction over
# every ray, a tensor created on the default device or in the default dtype...), then a few closed forms
# that the Monte Carlo tests above cannot resolve.

BATCH = (2, 4)  # a (2, 4, ...) batch must equal the same 8 rays computed as a flat (8, ...) batch


def nerf_calls(make, s=5):
    """name -> (function of the tensors, tensors): every public function of the NeRF math modules."""
    rays = int(math.prod(BATCH))
    tdist = torch.sort(2 + 4 * make(rays, s + 1), dim=-1).values
    dirs = make(rays, 3) - 0.5
    unit = l2_normalize(dirs)
    w = make(rays, s) ** 2
    return {
        "pos_enc": (lambda x: pos_enc(x, 0, 4), [dirs]),
        "ipe": (lambda m, v: integrated_pos_enc(m, v, 1, 4), [dirs, 0.1 * w[:, :3]]),
        "cast_rays_diag": (
            lambda t, o, d, r: cast_rays(t, o, d, r, diag=True),
            [tdist, dirs, dirs, w[:, :1]],
        ),
        "cast_rays_full": (
            lambda t, o, d, r: cast_rays(t, o, d, r, diag=False),
            [tdist, dirs, dirs, w[:, :1]],
        ),
        "alpha": (compute_alpha_weights, [w, tdist, dirs]),
        "render": (
            lambda rgb, wt, t: volumetric_rendering(
                rgb.unflatten(-1, (s, 3)), 0.3 * wt, t, 0.5 * rgb[..., :3]
            ),
            [make(rays, s * 3), w, tdist],
        ),
        "blur": (lambda wt: blur_weights(wt, 0.01), [w]),
        "stratified": (
            lambda n, f: stratified_samples(n, f, 6, True, generator=gen(1)),
            [2 + make(rays, 1), 5 + make(rays, 1)],
        ),
        "stratified_lindisp": (
            lambda n, f: stratified_samples(n, f, 6, False, lindisp=True),
            [2 + make(rays, 1), 5 + make(rays, 1)],
        ),
        "pdf": (lambda b, wt: sample_pdf(b, wt, 7, True, generator=gen(2)), [tdist, w]),
        "pdf_det": (lambda b, wt: sample_pdf(b, wt, 7, False), [tdist, w]),
        "resample_mip": (lambda t, wt: resample_tdist(t, wt, 7, True, 0.01, generator=gen(3)), [tdist, w]),
        "resample_nerf": (lambda t, wt: resample_tdist(t, wt, 7, True, None, generator=gen(3)), [tdist, w]),
        "sph": (lambda u: complex_sph_harm(u, [(0, 0), (2, 1), (4, 4), (3, 0)]), [unit]),
        "real_sph": (lambda u: real_sph_harm(u, 3), [unit]),
        "ide": (lambda u, k: integrated_dir_enc(u, k, 3), [unit, w[:, :1]]),
        "reflect": (reflect, [unit, l2_normalize(dirs.flip(-1))]),
    }


def flat_outputs(out):
    if isinstance(out, dict):
        return [out[k] for k in sorted(out)]
    return list(out) if isinstance(out, tuple) else [out]


def test_nerf_math_is_batched_over_leading_dimensions():
    g = gen(20)
    make = lambda *shape: torch.rand(*shape, generator=g, dtype=F64)  # noqa: E731
    for name, (fn, args) in nerf_calls(make).items():
        flat = flat_outputs(fn(*args))
        batched = flat_outputs(fn(*(a.unflatten(0, BATCH) for a in args)))
        for f, b in zip(flat, batched, strict=True):
            assert b.shape == (*BATCH, *f.shape[1:]), name
            assert_within(b.flatten(0, 1), f, 1e-12)


@pytest.mark.parametrize("dtype", [torch.float16, torch.float64])
def test_nerf_math_keeps_dtype_and_device(dtype):
    """On the meta device (shapes only): a tensor made on the CPU or in float32 inside any function fails
    to combine with the inputs or changes the output's dtype."""
    make = lambda *shape: torch.rand(*shape, dtype=F64).to("meta", dtype)  # noqa: E731
    for name, (fn, args) in nerf_calls(make).items():
        for out in flat_outputs(fn(*args)):
            assert (out.device.type, out.dtype) == ("meta", dtype), name


def test_random_sampling_follows_the_generator():
    """Seeded draws are reproducible (they use the given generator) and actually random when asked."""
    near, far = torch.full((3, 1), 2.0), torch.full((3, 1), 6.0)
    tdist = stratified_samples(near, far, 8, randomized=False)
    w = torch.rand(3, 8, generator=gen(21))
    for fn in (
        lambda r, g: stratified_samples(near, far, 8, r, generator=g),
        lambda r, g: sample_pdf(tdist, w, 8, r, generator=g),
        lambda r, g: resample_tdist(tdist, w, 8, r, 0.01, generator=g),
        lambda r, g: resample_tdist(tdist, w, 8, r, None, generator=g),
    ):
        torch.manual_seed(0)
        a = fn(True, gen(5))
        b = fn(True, gen(5))  # the global RNG has moved on: equal only if the generator is used
        assert torch.equal(a, b)
        assert not torch.equal(a, fn(False, None))


def test_defaults_of_pos_enc_and_cast_rays():
    x = torch.tensor([[0.3, -1.2, 2.0]], dtype=F64)
    assert torch.equal(pos_enc(x, 0, 2), pos_enc(x, 0, 2, append_identity=True))
    tdist = torch.tensor([[1.0, 2.0, 4.0]], dtype=F64)
    assert cast_rays(tdist, x, x, torch.ones(1, 1, dtype=F64))[1].shape == (1, 2, 3)  # diagonal by default


def test_frustum_of_a_short_direction_vector():
    # ||d|| < 1: the lifted covariance must use ||d||^2 itself (it is clamped only near 0).
    d = torch.tensor([0.3, 0.0, -0.4], dtype=F64)  # ||d||^2 = 0.25
    t0, t1, radius = 1.0, 2.0, 0.1
    _, cov = cast_rays(
        torch.tensor([[t0, t1]], dtype=F64),
        torch.zeros(1, 3, dtype=F64),
        d[None],
        torch.tensor([[radius]], dtype=F64),
        diag=False,
    )
    _, var_t, var_r = paper_frustum_moments(t0, t1, radius)
    d_outer = torch.outer(d, d)
    assert_within(cov[0, 0], var_t * d_outer + var_r * (torch.eye(3, dtype=F64) - d_outer / 0.25), 1e-12)


def test_volumetric_depth_of_partial_and_last_interval_weights():
    tdist = torch.tensor([[1.0, 2.0, 4.0, 8.0]], dtype=F64)
    rgb = torch.zeros(1, 3, 3, dtype=F64)
    bg = torch.zeros(3, dtype=F64)
    out = volumetric_rendering(rgb, torch.tensor([[0.2, 0.3, 0.0]], dtype=F64), tdist, bg)
    assert out["depth"].item() == pytest.approx((0.2 * 1.5 + 0.3 * 3.0) / 0.5)  # normalised by acc = 0.5
    last = volumetric_rendering(rgb, torch.tensor([[0.0, 0.0, 1.0]], dtype=F64), tdist, bg)
    assert last["depth"].item() == pytest.approx(6.0)  # the last midpoint, inside [t_0, t_S]


def test_sample_pdf_skips_an_empty_first_bin():
    bins = torch.tensor([[0.0, 1.0, 2.0, 3.0]])
    samples = sample_pdf(bins, torch.tensor([[0.0, 1.0, 1.0]]), 5, randomized=False)
    assert samples[0, 0].item() == pytest.approx(1.0)  # u = 0 maps to the start of the mass, not to 0
    assert bool((samples >= 1.0).all())


def test_real_sph_harm_closed_form_and_ide_degrees():
    x, y, z = 0.48, -0.6, 0.64
    feats = real_sph_harm(torch.tensor([[x, y, z]], dtype=F64), 1)[0]
    c0, c1 = 0.5 / math.sqrt(math.pi), math.sqrt(3 / (4 * math.pi))
    # [Y_0^0, Y_1^0, sqrt(2) Re Y_1^1, sqrt(2) Im Y_1^1] with the Condon-Shortley phase
    assert_within(feats, torch.tensor([c0, c1 * z, -c1 * x, -c1 * y], dtype=F64), 1e-12)
    assert ide_degrees(1) == [(1, 0), (1, 1)]


def test_rays_and_intervals_do_not_mix():
    """Every quantity of a ray (and of an interval) depends on that ray (interval) alone: all at once
    equals one at a time. The batching test above cannot see a reduction over *all* rays (`dim=None`),
    nor an interval built from the wrong endpoint, since those act alike on a flat and a batched input."""
    g = gen(30)
    tdist = torch.tensor([[2.0, 2.5, 3.5, 5.0], [1.0, 1.2, 1.3, 4.0]], dtype=F64)
    dirs = torch.tensor([[0.3, -0.2, 0.9], [2.0, 1.0, -0.5]], dtype=F64)  # different lengths
    origins = torch.rand(2, 3, generator=g, dtype=F64)
    radii = torch.tensor([[0.01], [0.03]], dtype=F64)
    for diag in (True, False):
        means, covs = cast_rays(tdist, origins, dirs, radii, diag)
        for r in range(2):
            for i in range(3):
                one = cast_rays(
                    tdist[r : r + 1, i : i + 2], origins[r : r + 1], dirs[r : r + 1], radii[r : r + 1], diag
                )
                assert_within(means[r, i], one[0][0, 0], 1e-12)
                assert_within(covs[r, i], one[1][0, 0], 1e-12)
    density = 3 * torch.rand(2, 3, generator=g, dtype=F64)
    rgb = torch.rand(2, 3, 3, generator=g, dtype=F64)
    bg = torch.tensor([1.0, 0.5, 0.0], dtype=F64)
    weights, _, _ = compute_alpha_weights(density, tdist, dirs)
    out = volumetric_rendering(rgb, weights, tdist, bg)
    for r in range(2):
        w_one, _, _ = compute_alpha_weights(density[r : r + 1], tdist[r : r + 1], dirs[r : r + 1])
        assert_within(weights[r], w_one[0], 1e-12)
        one = volumetric_rendering(rgb[r : r + 1], w_one, tdist[r : r + 1], bg)
        for key, value in one.items():
            assert_within(out[key][r], value[0], 1e-12)


def test_sample_pdf_pads_an_empty_ray_inside_a_batch():
    # A ray whose weights are all zero gets a uniform pdf: its samples are the quantiles themselves on
    # [0, 1] bins, whatever the batch shape around it.
    bins = torch.linspace(0.0, 1.0, 5, dtype=F64).expand(2, 3, 5)
    weights = torch.rand(2, 3, 4, generator=gen(31), dtype=F64)
    weights[1, 2] = 0.0
    batched = sample_pdf(bins, weights, 6, randomized=False)
    assert_within(
        batched.reshape(6, 6), sample_pdf(bins.reshape(6, 5), weights.reshape(6, 4), 6, False), 1e-12
    )
    assert_within(batched[1, 2], torch.linspace(0.0, 1.0 - 1e-5, 6, dtype=F64), 1e-9)


# Surviving mutants of the NeRF math (bash scripts/mutation.sh nerf), all equivalent here:
# - sample_pdf: the clamps of `frac` to [0, 1], of `above` to the last index, of the cdf to 1 and of the
#   quantiles to 1 - eps, and the fallbacks where a bin has zero width (12 mutants, e.g. clamp(0.0, 2.0),
#   `denom >= 0`, max=1.0 + eps): each guards a bound the construction already keeps (u < 1 = cdf[-1],
#   cdf_0 <= u < cdf_1 where denom > 0), and a zero-width bin is never the one a quantile falls in;
#   `arange(n, dtype=None)` (2): int64 strata promote to the jitter's dtype.
# - resample_tdist `torch.sort(..., dim=-1)` -> `torch.sort(...)`: -1 is the default.
# - complex_sph_harm: the float64 polynomial's `dtype=`/`device=` arguments dropped or None (9 mutants),
#   and the `"mps"` test misspelt or forced False (3): they change nothing on a CPU (or CUDA) device, and
#   the meta-device test above does not check devices; `xyz[..., 2:4]` is `2:3` on 3-vectors.
# - sph_harm_poly_coeffs `(-1) ** (m + l - j)` -> `(-1) ** (m + l + j)`: the exponents differ by 2j.
