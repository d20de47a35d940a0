"""Directional encodings of Ref-NeRF (Verbin et al. 2022): reflection, spherical harmonics and the
integrated directional encoding (IDE), as pure batched functions.

Spherical harmonics (complex, orthonormal, Condon-Shortley phase) are evaluated in closed form, without
trigonometric functions, for unit vectors (x, y, z):

    Y_l^m(x, y, z) = (x + i y)^m * sum_k c_{l,m,k} z^k,        m >= 0,

because sin^m(theta) e^{i m phi} = (x + i y)^m. The coefficients follow from Rodrigues' formula
P_l(z) = 1 / (2^l l!) d^l/dz^l (z^2 - 1)^l and P_l^m(z) = (-1)^m (1 - z^2)^{m/2} d^m/dz^m P_l(z):

    d^{l+m}/dz^{l+m} (z^2 - 1)^l = sum_j C(l, j) (-1)^(l-j) (2j)! / (2j - l - m)! z^(2j - l - m),

so c_{l,m,k} = N_lm (-1)^m C(l, j) (-1)^(l-j) (2j)! / (2^l l! k!) for k = 2j - l - m >= 0, with
N_lm = sqrt((2l + 1) / (4 pi) * (l - m)! / (l + m)!). They are computed exactly in rational arithmetic
(only the final square root is rounded), collected in a (k, feature) matrix, and the polynomial part of
all harmonics is one matmul of the powers of z with it.
"""

from __future__ import annotations

import functools
import math
from fractions import Fraction

import torch
from torch import Tensor

#: Largest `deg_view` accepted: l = 2^(deg_view-1) = 16. Beyond that the monomial form of P_l^m
#: cancels catastrophically in float32 (the same limit as Ref-NeRF's released code).
MAX_DEG_VIEW = 5


def l2_normalize(x: Tensor, eps: float = torch.finfo(torch.float32).eps) -> Tensor:
    """x / ||x|| along the last axis; the squared norm is clamped to `eps` (no NaN, finite gradient at 0)."""
    return x / torch.sqrt(torch.clamp((x**2).sum(dim=-1, keepdim=True), min=eps))


def reflect(viewdirs: Tensor, normals: Tensor) -> Tensor:
    """Reflection of `viewdirs` about `normals` (Ref-NeRF Sec. 3): omega_r = 2 (omega_o . n) n - omega_o.

    `viewdirs` (omega_o) points away from the surface (towards the camera, i.e. minus the ray direction);
    `normals` are unit vectors. Shapes broadcast, the last axis is 3.
    """
    return 2.0 * (viewdirs * normals).sum(dim=-1, keepdim=True) * normals - viewdirs


def ide_degrees(deg_view: int) -> list[tuple[int, int]]:
    """The (l, m) pairs the IDE uses (Ref-NeRF Sec. 3.1): l in {1, 2, 4, ..., 2^(deg_view-1)},
    m in 0..l (the m < 0 harmonics are the complex conjugates, up to sign, of the m > 0 ones, so the real
    and imaginary parts of m >= 0 span the same space)."""
    if not 1 <= deg_view <= MAX_DEG_VIEW:
        raise ValueError(f"deg_view must be in [1, {MAX_DEG_VIEW}], got {deg_view}")
    return [(2**i, m) for i in range(deg_view) for m in range(2**i + 1)]


def sph_harm_poly_coeffs(l: int, m: int) -> list[float]:  # noqa: E741 (l is the standard SH degree)
    """c_k, k = 0..l-m, with Y_l^m(x, y, z) = (x + i y)^m * sum_k c_k z^k (see the module docstring)."""
    if not 0 <= m <= l:
        raise ValueError(f"expected 0 <= m <= l, got l={l}, m={m}")
    norm_sq = Fraction((2 * l + 1) * math.factorial(l - m), math.factorial(l + m))  # times 1 / (4 pi)
    coeffs = [0.0] * (l - m + 1)
    for j in range((l + m + 1) // 2, l + 1):
        k = 2 * j - l - m
        rational = Fraction(
            (-1) ** (m + l - j) * math.comb(l, j) * math.factorial(2 * j),
            2**l * math.factorial(l) * math.factorial(k),
        )
        coeffs[k] = float(rational) * math.sqrt(float(norm_sq) / (4 * math.pi))
    return coeffs


@functools.lru_cache(maxsize=16)
def _coeff_matrix(lms: tuple[tuple[int, int], ...]) -> Tensor:
    """(max_l + 1, len(lms)) float64 matrix: column f holds the z-polynomial coefficients of lms[f]."""
    max_l = max(deg for deg, _ in lms)
    mat = torch.zeros(max_l + 1, len(lms), dtype=torch.float64)
    for f, (l, m) in enumerate(lms):  # noqa: E741
        mat[: l - m + 1, f] = torch.tensor(sph_harm_poly_coeffs(l, m), dtype=torch.float64)
    return mat


def complex_sph_harm(
    xyz: Tensor, lms: list[tuple[int, int]] | tuple[tuple[int, int], ...]
) -> tuple[Tensor, Tensor]:
    """Real and imaginary parts of Y_l^m(xyz) for each (l, m >= 0) in `lms`: two (..., len(lms)) tensors.

    `xyz` (..., 3) must be unit vectors. Batched: the powers of z times a coefficient matrix, and
    (x + i y)^m by the recurrence (a + i b)(x + i y), one step per m (at most max m steps, never per ray).
    """
    lms = tuple(lms)
    # The monomial form of P_l^m cancels: at l = 16 float32 loses ~1e-2, so the polynomial part is
    # evaluated in float64 (a (..., l+1) @ (l+1, F) matmul, cheap next to the MLPs) and cast back.
    poly_dtype = xyz.dtype if xyz.device.type == "mps" else torch.float64  # MPS has no float64
    mat = _coeff_matrix(lms).to(dtype=poly_dtype, device=xyz.device)
    x, y, z = xyz[..., 0:1], xyz[..., 1:2], xyz[..., 2:3]
    z_pows = z.to(poly_dtype) ** torch.arange(mat.shape[0], dtype=poly_dtype, device=xyz.device)
    poly = (z_pows @ mat).to(xyz.dtype)  # (..., F)
    max_m = max(m for _, m in lms)
    re, im = [torch.ones_like(x)], [torch.zeros_like(x)]
    for _ in range(max_m):
        a, b = re[-1], im[-1]
        re.append(a * x - b * y)
        im.append(a * y + b * x)
    m_idx = torch.tensor([m for _, m in lms], device=xyz.device)
    re_m = torch.cat(re, dim=-1).index_select(-1, m_idx)
    im_m = torch.cat(im, dim=-1).index_select(-1, m_idx)
    return re_m * poly, im_m * poly


def real_sph_harm(xyz: Tensor, l_max: int) -> Tensor:
    """Orthonormal real spherical harmonics up to degree l_max: (..., (l_max + 1)^2), ordered by l then
    [Y_l^0, sqrt(2) Re Y_l^1, sqrt(2) Im Y_l^1, ..., sqrt(2) Re Y_l^l, sqrt(2) Im Y_l^l]."""
    lms = [(l, m) for l in range(l_max + 1) for m in range(l + 1)]  # noqa: E741
    re, im = complex_sph_harm(xyz, lms)
    cols = []
    for f, (_, m) in enumerate(lms):
        if m == 0:
            cols.append(re[..., f])
        else:
            cols += [math.sqrt(2) * re[..., f], math.sqrt(2) * im[..., f]]
    return torch.stack(cols, dim=-1)


def ide_attenuation(deg_view: int, kappa_inv: Tensor) -> Tensor:
    """exp(-l (l + 1) / 2 * kappa_inv) per IDE feature (..., F): Ref-NeRF's (Eq. 7-8) approximation of the
    vMF expectation E[Y_l^m(omega)] = A_l(kappa) Y_l^m(mu)."""
    l = torch.tensor([l for l, _ in ide_degrees(deg_view)], dtype=kappa_inv.dtype, device=kappa_inv.device)  # noqa: E741
    return torch.exp(-0.5 * l * (l + 1) * kappa_inv)


def integrated_dir_enc(xyz: Tensor, kappa_inv: Tensor, deg_view: int) -> Tensor:
    """Integrated directional encoding (Ref-NeRF, Verbin et al. 2022, Eq. 7-8).

    IDE(omega_r, kappa) = {E_{omega ~ vMF(omega_r, kappa)}[Y_l^m(omega)]} ~= {exp(-l (l + 1) / (2 kappa))
    Y_l^m(omega_r)} for l in {1, 2, 4, ..., 2^(deg_view-1)}, m in 0..l; returned as
    [real parts, imaginary parts]: 2 * sum_l (l + 1) features (72 for deg_view = 5; the imaginary parts
    of the m = 0 harmonics are identically zero, kept for the released layout).

    Args:
        xyz: (..., 3) unit directions (the reflected view directions).
        kappa_inv: (..., 1) 1 / kappa, the roughness (0: a plain SH encoding).
    """
    re, im = complex_sph_harm(xyz, ide_degrees(deg_view))
    att = ide_attenuation(deg_view, kappa_inv)
    return torch.cat([re * att, im * att], dim=-1)


def dir_enc(xyz: Tensor, deg_view: int) -> Tensor:
    """The directional encoding without integration: `integrated_dir_enc` with kappa_inv = 0."""
    return integrated_dir_enc(xyz, torch.zeros_like(xyz[..., :1]), deg_view)


def ide_dim(deg_view: int) -> int:
    """Number of IDE features: 2 * sum over l of (l + 1)."""
    return 2 * len(ide_degrees(deg_view))
