"""Positional encodings and the Gaussian approximation of cone-traced frusta (pure functions).

- `pos_enc`: NeRF's positional encoding gamma(p) (Mildenhall et al. 2020, Eq. 4), written as in the
  released code and multinerf: frequencies 2^k without the factor pi, the cosines as sin(x + pi/2).
- `integrated_pos_enc`: mip-NeRF's integrated positional encoding (Barron et al. 2021, Eq. 14-16), the
  expected PE of a Gaussian with diagonal covariance.
- `conical_frustum_to_gaussian` / `cast_rays`: the mean and covariance of a conical frustum
  (mip-NeRF Eq. 7-8, with the numerically stable reparameterisation of its appendix).

Every function takes and returns torch tensors, is batched over the leading dimensions and has no Python
loop over rays or samples.

The models do not call these functions themselves: they hold `Encoding` objects, built from the
`model.position_encoding` / `model.view_encoding` configs (`_target_` sub-configs, conf/encoding/), that
call them. An encoding knows its output size (`out_dim`, which sizes the MLP's input) and says what it
reads (`reads`), so that a model computes the right per-sample inputs without knowing which encoding it
holds:

- `PositionalEncoding` reads a point (NeRF's interval midpoints, or a view direction): `pos_enc`.
- `IntegratedPositionalEncoding` reads a Gaussian (mip-NeRF's conical frustums): `integrated_pos_enc`.
- `IntegratedDirectionalEncoding` reads a von Mises-Fisher lobe (Ref-NeRF's reflected direction and
  roughness): `directional.integrated_dir_enc`.

A new encoding is a subclass of `Encoding` (anywhere importable) and a `_target_` config naming it.
"""

from __future__ import annotations

from typing import ClassVar

import torch
from torch import Tensor, nn

from src.models.nerf.directional import MAX_DEG_VIEW, ide_dim, integrated_dir_enc

#: What an encoding reads, as the names of its `forward` arguments (every tensor (..., k), batched):
#: "point": x (..., 3), a point or a direction (NeRF: the interval midpoints o + t_mid d; the view direction);
#: "gaussian": means (..., 3) and diagonal covs (..., 3), a conical frustum's Gaussian (mip-NeRF Eq. 7-8);
#: "vmf": directions (..., 3) unit and kappa_inv (..., 1), a von Mises-Fisher lobe (Ref-NeRF Sec. 3.1).
#: The first name is the position a sample stands for (the occupancy grid's query, Ref-NeRF's normals).
READS: dict[str, tuple[str, ...]] = {
    "point": ("x",),
    "gaussian": ("means", "covs"),
    "vmf": ("directions", "kappa_inv"),
}


def _scales(min_deg: int, max_deg: int, like: Tensor) -> Tensor:
    """2^[min_deg, max_deg) in the dtype/device of `like`."""
    return 2.0 ** torch.arange(min_deg, max_deg, dtype=like.dtype, device=like.device)


def pos_enc(x: Tensor, min_deg: int, max_deg: int, append_identity: bool = True) -> Tensor:
    """NeRF positional encoding (Mildenhall et al. 2020, Eq. 4).

    With scales s_k = 2^k, k in [min_deg, max_deg) and y = [s_k * x] (degree-major, coordinate-minor),
    returns cat([x, sin(y), cos(y)]) (the identity first when `append_identity`; multinerf writes cos(y)
    as sin(y + pi/2), equal up to rounding), i.e.
    D * (2 * (max_deg - min_deg) + append_identity) features for x of shape (..., D).
    """
    scales = _scales(min_deg, max_deg, x)
    scaled = (x[..., None, :] * scales[:, None]).reshape(*x.shape[:-1], -1)
    four_feat = torch.cat([torch.sin(scaled), torch.cos(scaled)], dim=-1)
    return torch.cat([x, four_feat], dim=-1) if append_identity else four_feat


def expected_sin(mean: Tensor, var: Tensor) -> Tensor:
    """E[sin(x)] for x ~ N(mean, var): exp(-var / 2) * sin(mean) (mip-NeRF Sec. 3.1)."""
    return torch.exp(-0.5 * var) * torch.sin(mean)


def integrated_pos_enc(mean: Tensor, var: Tensor, min_deg: int, max_deg: int) -> Tensor:
    """Integrated positional encoding (mip-NeRF, Barron et al. 2021, Eq. 14-16).

    For x ~ N(mean, diag(var)), the PE basis P = diag(2^k) lifts the Gaussian to
    mu_gamma = P mean, diag(Sigma_gamma) = 4^k var, and the expected encoding is
    [sin(mu_gamma) * exp(-diag(Sigma_gamma) / 2), cos(mu_gamma) * exp(-diag(Sigma_gamma) / 2)],
    with the feature order of `pos_enc(..., append_identity=False)`: zero variance gives exactly that PE.
    """
    scales = _scales(min_deg, max_deg, mean)
    shape = (*mean.shape[:-1], -1)
    scaled_mean = (mean[..., None, :] * scales[:, None]).reshape(shape)
    scaled_var = (var[..., None, :] * scales[:, None] ** 2).reshape(shape)
    # multinerf evaluates sin on [mu, mu + pi/2] against the variance twice; one damping factor shared by
    # sin and cos halves the exp calls and skips two concatenations (2.3x faster at L = 16 on CPU), and
    # cos(mu) avoids rounding mu + pi/2 where 2^k mu is large.
    damping = torch.exp(-0.5 * scaled_var)
    return torch.cat([damping * torch.sin(scaled_mean), damping * torch.cos(scaled_mean)], dim=-1)


def lift_gaussian(
    d: Tensor, t_mean: Tensor, t_var: Tensor, r_var: Tensor, diag: bool
) -> tuple[Tensor, Tensor]:
    """A 1D Gaussian along the ray and an isotropic one across it, lifted to 3D (mip-NeRF Eq. 8).

    mu = t_mean * d, Sigma = t_var * d d^T + r_var * (I - d d^T / ||d||^2).

    Args:
        d: (..., 3) ray directions (any length: t is the ray parameter, x = o + t d).
        t_mean, t_var, r_var: (..., S) per-interval moments along / across the ray.
        diag: return only the diagonal of Sigma, (..., S, 3), instead of (..., S, 3, 3).

    Returns:
        (mean (..., S, 3) relative to the ray origin, covariance).
    """
    mean = d[..., None, :] * t_mean[..., None]
    d_mag_sq = torch.clamp((d**2).sum(dim=-1, keepdim=True), min=1e-10)
    if diag:
        d_outer_diag = d**2
        null_outer_diag = 1.0 - d_outer_diag / d_mag_sq
        cov = t_var[..., None] * d_outer_diag[..., None, :] + r_var[..., None] * null_outer_diag[..., None, :]
        return mean, cov
    d_outer = d[..., :, None] * d[..., None, :]
    eye = torch.eye(d.shape[-1], dtype=d.dtype, device=d.device)
    null_outer = eye - d[..., :, None] * (d / d_mag_sq)[..., None, :]
    cov = (
        t_var[..., None, None] * d_outer[..., None, :, :]
        + r_var[..., None, None] * null_outer[..., None, :, :]
    )
    return mean, cov


def conical_frustum_to_gaussian(
    d: Tensor, t0: Tensor, t1: Tensor, base_radius: Tensor, diag: bool
) -> tuple[Tensor, Tensor]:
    """Mean and covariance of the conical frustum {o + t d + r u : t in [t0, t1], u _|_ d, |r| <= t R}.

    The cone has its apex at the ray origin and radius t * base_radius at ray parameter t. Its moments
    (mip-NeRF, Barron et al. 2021, Eq. 7) are evaluated with the stable form of the appendix, in terms of
    the interval midpoint mu = (t0 + t1) / 2 and half-width hw = (t1 - t0) / 2:

        t_mean = mu + 2 mu hw^2 / (3 mu^2 + hw^2)
        t_var  = hw^2 / 3 - (4 / 15) hw^4 (12 mu^2 - hw^2) / (3 mu^2 + hw^2)^2
        r_var  = R^2 (mu^2 / 4 + (5 / 12) hw^2 - (4 / 15) hw^4 / (3 mu^2 + hw^2))

    then lifted to 3D by `lift_gaussian` (Eq. 8).

    Args:
        d: (..., 3) ray directions; t0, t1: (..., S) interval ends; base_radius: (..., 1) (or
            broadcastable to t0) cone radius at t = 1.
    """
    mu = (t0 + t1) / 2
    hw = (t1 - t0) / 2
    denom = 3 * mu**2 + hw**2
    t_mean = mu + (2 * mu * hw**2) / denom
    t_var = hw**2 / 3 - (4 / 15) * (hw**4 * (12 * mu**2 - hw**2)) / denom**2
    r_var = base_radius**2 * (mu**2 / 4 + (5 / 12) * hw**2 - (4 / 15) * hw**4 / denom)
    return lift_gaussian(d, t_mean, t_var, r_var, diag)


def cast_rays(
    tdist: Tensor, origins: Tensor, directions: Tensor, radii: Tensor, diag: bool = True
) -> tuple[Tensor, Tensor]:
    """The Gaussians of every interval [tdist[i], tdist[i+1]] of every ray (mip-NeRF Sec. 3.1).

    Args:
        tdist: (N, S+1) sorted interval endpoints (ray parameters).
        origins, directions: (N, 3); radii: (N, 1), the cone radius at t = 1.
        diag: diagonal covariances (N, S, 3), as the IPE needs, or full ones (N, S, 3, 3).

    Returns:
        (means (N, S, 3) in world space, covs).
    """
    means, covs = conical_frustum_to_gaussian(directions, tdist[..., :-1], tdist[..., 1:], radii, diag)
    return means + origins[..., None, :], covs


def position_key(reads: str) -> str:
    """The input of an encoding that reads `reads` that is the sample position ("x" or "means")."""
    return READS[reads][0]


# --- encodings as objects ------------------------------------------------------------------------------


class Encoding(nn.Module):
    """An input encoding of a radiance field: `forward(*inputs) -> (..., out_dim)`.

    Subclasses set `reads` (a key of `READS`: what `forward` takes) and, in `__init__`, `out_dim` (the
    number of output features for their settings; the MLPs are sized by it). They raise ValueError naming
    the argument (`"max_deg: ..."`) for a setting out of range. An encoding holds no trained parameters of
    its own in the built-in classes (their state dicts are the MLPs' alone).
    """

    reads: ClassVar[str]
    #: Dimension of the vectors it encodes (points and directions: 3).
    in_dim: ClassVar[int] = 3
    out_dim: int


def _check_degrees(min_deg: int, max_deg: int) -> None:
    if min_deg < 0:
        raise ValueError(f"min_deg: expected >= 0, got {min_deg}")
    if max_deg <= min_deg:
        raise ValueError(f"max_deg: expected > min_deg ({min_deg}), got {max_deg}")


class PositionalEncoding(Encoding):
    """NeRF's positional encoding gamma(x) (Mildenhall et al. 2020, Eq. 4; `pos_enc`) of a point or a
    direction: frequencies 2^k, k in [min_deg, max_deg), the input itself first when `identity`.
    out_dim = 3 (2 (max_deg - min_deg) + identity): 63 for NeRF's points (L = 10), 27 for its view
    directions (L = 4)."""

    reads = "point"

    def __init__(self, min_deg: int, max_deg: int, identity: bool = True) -> None:
        super().__init__()
        _check_degrees(min_deg, max_deg)
        self.min_deg, self.max_deg, self.identity = min_deg, max_deg, identity
        self.out_dim = self.in_dim * (2 * (max_deg - min_deg) + int(identity))

    def forward(self, x: Tensor) -> Tensor:
        return pos_enc(x, self.min_deg, self.max_deg, append_identity=self.identity)

    def extra_repr(self) -> str:
        return f"degrees [{self.min_deg}, {self.max_deg}), identity={self.identity}, out_dim={self.out_dim}"


class IntegratedPositionalEncoding(Encoding):
    """mip-NeRF's integrated positional encoding (Barron et al. 2021, Eq. 14-16; `integrated_pos_enc`) of
    a conical frustum's Gaussian: the expected PE over the Gaussian, without the identity term.
    out_dim = 2 * 3 (max_deg - min_deg): 96 at mip-NeRF's degrees 0-15."""

    reads = "gaussian"

    def __init__(self, min_deg: int, max_deg: int) -> None:
        super().__init__()
        _check_degrees(min_deg, max_deg)
        self.min_deg, self.max_deg = min_deg, max_deg
        self.out_dim = 2 * self.in_dim * (max_deg - min_deg)

    def forward(self, means: Tensor, covs: Tensor) -> Tensor:
        return integrated_pos_enc(means, covs, self.min_deg, self.max_deg)

    def extra_repr(self) -> str:
        return f"degrees [{self.min_deg}, {self.max_deg}), out_dim={self.out_dim}"


class IntegratedDirectionalEncoding(Encoding):
    """Ref-NeRF's integrated directional encoding (Verbin et al. 2022, Eq. 7-8;
    `directional.integrated_dir_enc`) of a von Mises-Fisher lobe: the attenuated spherical harmonics
    Y_l^m, l in {1, 2, 4, ..., 2^(deg_view - 1)}, m in 0..l, real and imaginary parts.
    out_dim = 2 sum_l (l + 1): 72 at Ref-NeRF's deg_view = 5."""

    reads = "vmf"

    def __init__(self, deg_view: int) -> None:
        super().__init__()
        if not 1 <= deg_view <= MAX_DEG_VIEW:
            raise ValueError(
                f"deg_view: expected an integer in [1, {MAX_DEG_VIEW}] (l <= 16), got {deg_view}"
            )
        self.deg_view = deg_view
        self.out_dim = ide_dim(deg_view)

    def forward(self, directions: Tensor, kappa_inv: Tensor) -> Tensor:
        return integrated_dir_enc(directions, kappa_inv, self.deg_view)

    def extra_repr(self) -> str:
        return f"deg_view={self.deg_view}, out_dim={self.out_dim}"
