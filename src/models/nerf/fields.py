"""The MLPs of NeRF / mip-NeRF (`NerfMLP`) and Ref-NeRF (`RefNerfMLP`).

Layout shared by both (NeRF, Mildenhall et al. 2020, Fig. 7 / Appendix A; mip-NeRF and Ref-NeRF keep it):
a ReLU trunk of `depth` fully connected layers of `width` units, with the encoded input concatenated to the
output of every layer i > 0 with i % skip_layer == 0 (skip_layer = 4 at depth 8: the fifth layer's
activation, as in the paper and multinerf), a density head, a linear bottleneck, and a view-dependent
MLP producing the colour. Weights are He-uniform initialised and biases zero (multinerf's choice).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from src.io.srgb import linear_to_srgb
from src.models.nerf.directional import l2_normalize, reflect
from src.models.nerf.encodings import (
    Encoding,
    IntegratedDirectionalEncoding,
    IntegratedPositionalEncoding,
    position_key,
)

ACTIVATIONS: dict[str, Callable[[Tensor], Tensor]] = {"relu": F.relu, "softplus": F.softplus}
#: Colour channels of every head.
RGB = 3


def padded_sigmoid(x: Tensor, padding: float) -> Tensor:
    """sigmoid(x) * (1 + 2p) - p: colours in [-p, 1 + p] (mip-NeRF Sec. 4, p = 0.001; p = 0 is NeRF's)."""
    return torch.sigmoid(x) * (1 + 2 * padding) - padding


def _init_linear(layer: nn.Linear) -> nn.Linear:
    nn.init.kaiming_uniform_(layer.weight, nonlinearity="relu")  # He-uniform: U(+-sqrt(6 / fan_in))
    nn.init.zeros_(layer.bias)
    return layer


def _activation(name: str) -> Callable[[Tensor], Tensor]:
    if name not in ACTIVATIONS:
        raise ValueError(f"unknown density activation {name!r}; expected one of {list(ACTIVATIONS)}")
    return ACTIVATIONS[name]


class SkipMLP(nn.Module):
    """`depth` Linear + ReLU layers of `width` units; the input is concatenated to the output of layer i
    whenever i > 0 and i % skip_layer == 0 (skip_layer None or 0: no skip). `out_dim` is the width of
    the last activation (width, plus in_dim if the last layer is followed by a skip).

    The input may come in pieces, `forward(a, b, ...)` meaning `forward(cat([a, b, ...], -1))`, and a
    piece may hold one row per ray, (..., 1, c), broadcast over the samples (NeRF's view encoding).
    The concatenations are never formed: a layer fed [h, x] computes W[:, :a] h + W[:, a:] x + bias
    (split matmuls accumulated in place, `torch.addmm`), a per-ray piece goes through its columns of W
    once per ray and is broadcast-added, and the ReLU runs in place. The same function as the
    straightforward cat / nn.Linear / ReLU form, in fewer passes over memory (the training step is
    bound by them at 256 channels, not by the matmuls); tests/test_nerf_fused.py checks outputs and
    gradients against that form.
    """

    def __init__(self, in_dim: int, depth: int, width: int, skip_layer: int | None) -> None:
        super().__init__()
        self.in_dim, self.depth, self.width, self.skip_layer = in_dim, depth, width, skip_layer
        layers, dim = [], in_dim
        for i in range(depth):
            layers.append(_init_linear(nn.Linear(dim, width)))
            dim = width + (in_dim if self._skip_after(i) else 0)
        self.layers = nn.ModuleList(layers)
        self.out_dim = dim

    def _skip_after(self, i: int) -> bool:
        return bool(self.skip_layer) and i > 0 and i % self.skip_layer == 0

    def forward(self, *pieces: Tensor) -> Tensor:
        lead = torch.broadcast_shapes(*(p.shape[:-1] for p in pieces))
        h: list[Tensor] = list(pieces)
        for i, layer in enumerate(self.layers):
            h = [fused_linear_relu(layer, h, lead)]
            if self._skip_after(i):
                h = h + list(pieces)
        return h[0] if len(h) == 1 else torch.cat([p.expand(*lead, p.shape[-1]) for p in h], dim=-1)


def fused_linear_relu(layer: nn.Linear, pieces: list[Tensor], lead: torch.Size) -> Tensor:
    """relu(layer(cat(pieces, -1))) without the cat: one `addmm` per piece into one output buffer (the
    bias added by the first), per-ray pieces (..., 1, c) multiplied once and broadcast-added, and an
    in-place ReLU. `lead` is the broadcast leading shape of the pieces; returns (*lead, out_features)."""
    rows = math.prod(lead)
    out: Tensor | None = None
    per_ray: list[tuple[Tensor, Tensor]] = []
    col = 0
    for piece in pieces:
        c = piece.shape[-1]
        weight = layer.weight[:, col : col + c] if len(pieces) > 1 else layer.weight
        col += c
        if piece.shape[:-1] != lead:
            per_ray.append((piece, weight))
            continue
        flat = piece.reshape(rows, c)
        if out is None:
            out = torch.addmm(layer.bias, flat, weight.t())
        else:  # autocast leaves in-place ops alone: under it, cast to the first addmm's dtype (else no-ops)
            out.addmm_(flat.to(out.dtype), weight.t().to(out.dtype))
    if col != layer.in_features:
        raise ValueError(f"inputs of {col} features for a layer of {layer.in_features}")
    if out is None:  # no per-sample piece
        out = layer.bias.expand(rows, layer.out_features).clone()
    if per_ray:  # out of place: an in-place add on the view would make autograd copy its gradient
        result = out.view(*lead, layer.out_features)
        for piece, weight in per_ray:
            result = result + F.linear(piece, weight)
        return result.relu_()
    return out.relu_().view(*lead, layer.out_features)


class NerfMLP(nn.Module):
    """NeRF's MLP (Mildenhall et al. 2020, Fig. 7), also mip-NeRF's (Barron et al. 2021, Sec. 4).

    trunk(encoded position) -> density = act(head + density_bias); bottleneck (linear) ++ encoded view
    direction -> view MLP -> rgb = padded_sigmoid(head, rgb_padding).
    NeRF: density_activation relu, density_bias 0, rgb_padding 0. mip-NeRF: softplus, -1, 0.001.

    forward(x_enc (..., S, pos_dim), view_enc (..., view_dim) per ray) ->
    {"density": (..., S), "rgb": (..., S, 3)}: the model encodes (its encodings' `out_dim` are
    pos_dim and view_dim).
    """

    def __init__(
        self,
        pos_dim: int,
        view_dim: int,
        *,
        depth: int = 8,
        width: int = 256,
        skip_layer: int | None = 4,
        bottleneck_width: int = 256,
        view_depth: int = 1,
        view_width: int = 128,
        view_skip_layer: int | None = None,
        density_activation: str = "relu",
        density_bias: float = 0.0,
        rgb_padding: float = 0.0,
    ) -> None:
        super().__init__()
        self.density_act = _activation(density_activation)
        self.density_bias, self.rgb_padding = density_bias, rgb_padding
        self.view_dim = view_dim  # the view MLP's per-ray input features (broadcast over the samples)
        self.trunk = SkipMLP(pos_dim, depth, width, skip_layer)
        self.density_head = _init_linear(nn.Linear(self.trunk.out_dim, 1))
        self.bottleneck = _init_linear(nn.Linear(self.trunk.out_dim, bottleneck_width))
        self.view_mlp = SkipMLP(bottleneck_width + view_dim, view_depth, view_width, view_skip_layer)
        self.rgb_head = _init_linear(nn.Linear(self.view_mlp.out_dim, RGB))

    def _density(self, h: Tensor) -> Tensor:
        return self.density_act(self.density_head(h)[..., 0] + self.density_bias)

    def density(self, x_enc: Tensor) -> Tensor:
        """The density alone (the trunk and density head; no view MLP), e.g. for an occupancy grid."""
        return self._density(self.trunk(x_enc))

    def forward(self, x_enc: Tensor, view_enc: Tensor) -> dict[str, Tensor]:
        h = self.trunk(x_enc)
        density = self._density(h)
        bottleneck = self.bottleneck(h)
        h = self.view_mlp(bottleneck, view_enc[..., None, :])  # the view encoding broadcast per ray
        return {"density": density, "rgb": padded_sigmoid(self.rgb_head(h), self.rgb_padding)}


class RefNerfMLP(nn.Module):
    """Ref-NeRF's spatial and directional MLPs (Verbin et al. 2022, Sec. 3-4, Fig. 2).

    Spatial MLP on the `position_encoding` of the samples (Ref-NeRF's: the IPE of the frustum Gaussians,
    mip-NeRF's encoding, degrees 0-15): density = act(raw + density_bias); diffuse colour
    c_d = sigmoid(raw - log 3) (linear, initialised around 0.25); specular tint s = sigmoid(raw);
    roughness rho = softplus(raw + roughness_bias) (the vMF's 1 / kappa); predicted normals
    n' = -normalize(raw_3); a linear bottleneck b.
    Normals n = -grad_x(raw density) / ||.|| (Ref-NeRF Sec. 3), by autograd w.r.t. the sample positions
    (the Gaussian means; `encodings.position_key`);
    `density_normals=False` skips them (multinerf's `disable_density_normals`: no `normals` output).

    Directional MLP on [b, view_encoding(omega_r, rho), n' . d] with omega_r = reflect(-d, n'), the
    reflection of the view direction about the predicted normal (the `view_encoding` reads a vMF lobe:
    Ref-NeRF's IDE, Eq. 7-8): specular colour c_s = sigmoid(raw);
    rgb = clip(linear_to_srgb(s * c_s + c_d), 0, 1), then the mip-NeRF padding.
    Without encodings given, the paper's: IPE degrees 0-15 and IDE deg_view 5.

    forward(samples, viewdirs (N, 3) unit), samples the position encoding's inputs (N, S, ...)
    (`encodings.READS`; the IPE's: {"means", "covs" diagonal}) -> per-sample dict with
    density (N, S), rgb, normals, normals_pred, diffuse, tint, specular (N, S, 3), roughness (N, S).
    The density gradient keeps its graph (double backprop, so the normal losses train the density)
    exactly when grad mode is on at the call; under `torch.no_grad` it is computed and detached.
    `torch.inference_mode` forbids autograd altogether: a RuntimeError says so.
    """

    def __init__(
        self,
        *,
        position_encoding: Encoding | None = None,
        view_encoding: Encoding | None = None,
        depth: int = 8,
        width: int = 256,
        skip_layer: int | None = 4,
        bottleneck_width: int = 128,
        view_depth: int = 8,
        view_width: int = 256,
        view_skip_layer: int | None = 4,
        density_activation: str = "softplus",
        density_bias: float = 0.5,
        roughness_bias: float = -1.0,
        rgb_padding: float = 0.001,
        density_normals: bool = True,
    ) -> None:
        super().__init__()
        self.position_encoding = position_encoding or IntegratedPositionalEncoding(0, 16)
        self.view_encoding = view_encoding or IntegratedDirectionalEncoding(5)  # reads "vmf"
        self.density_normals = density_normals
        self.density_act = _activation(density_activation)
        self.density_bias, self.roughness_bias, self.rgb_padding = density_bias, roughness_bias, rgb_padding
        self.trunk = SkipMLP(self.position_encoding.out_dim, depth, width, skip_layer)
        feat = self.trunk.out_dim
        self.density_head = _init_linear(nn.Linear(feat, 1))
        self.diffuse_head = _init_linear(nn.Linear(feat, RGB))
        self.tint_head = _init_linear(nn.Linear(feat, RGB))
        self.roughness_head = _init_linear(nn.Linear(feat, 1))
        self.normal_head = _init_linear(nn.Linear(feat, 3))
        self.bottleneck = _init_linear(nn.Linear(feat, bottleneck_width))
        dir_in = bottleneck_width + self.view_encoding.out_dim + 1  # [b, IDE, n' . d]
        self.view_mlp = SkipMLP(dir_in, view_depth, view_width, view_skip_layer)
        self.rgb_head = _init_linear(nn.Linear(self.view_mlp.out_dim, RGB))

    def _spatial(self, samples: Mapping[str, Tensor]) -> tuple[Tensor, Tensor]:
        h = self.trunk(self.position_encoding(**samples))
        return h, self.density_head(h)[..., 0]

    def density(self, samples: Mapping[str, Tensor]) -> Tensor:
        """The density alone (spatial MLP; no normals, no directional MLP), e.g. for an occupancy grid."""
        return self.density_act(self._spatial(samples)[1] + self.density_bias)

    def _spatial_with_normals(self, samples: Mapping[str, Tensor]) -> tuple[Tensor, Tensor, Tensor]:
        """The trunk features, raw density and density-gradient normals (graph kept iff grad mode is on)."""
        if torch.is_inference_mode_enabled():
            raise RuntimeError(
                "RefNerfMLP differentiates its density for the normals: run it under torch.no_grad, "
                "not torch.inference_mode"
            )
        keep_graph = torch.is_grad_enabled()
        key = position_key(self.position_encoding.reads)
        with torch.enable_grad():
            x = samples[key] if samples[key].requires_grad else samples[key].detach().requires_grad_(True)
            h, raw_density = self._spatial({**samples, key: x})
            (grad,) = torch.autograd.grad(raw_density.sum(), x, create_graph=keep_graph)
        if not keep_graph:
            h, raw_density, grad = h.detach(), raw_density.detach(), grad.detach()
        return h, raw_density, -l2_normalize(grad)

    def forward(self, samples: Mapping[str, Tensor], viewdirs: Tensor) -> dict[str, Tensor]:
        normals: dict[str, Tensor] = {}
        if self.density_normals:
            h, raw_density, normals["normals"] = self._spatial_with_normals(samples)
        else:
            h, raw_density = self._spatial(samples)
        normals_pred = -l2_normalize(self.normal_head(h))
        density = self.density_act(raw_density + self.density_bias)
        diffuse = torch.sigmoid(self.diffuse_head(h) - math.log(3.0))
        tint = torch.sigmoid(self.tint_head(h))
        roughness = F.softplus(self.roughness_head(h) + self.roughness_bias)  # (N, S, 1)
        bottleneck = self.bottleneck(h)

        d = viewdirs[..., None, :].expand_as(normals_pred)
        refdirs = reflect(-d, normals_pred)
        dir_features = self.view_encoding(refdirs, roughness)
        n_dot_d = (normals_pred * d).sum(dim=-1, keepdim=True)
        hv = self.view_mlp(bottleneck, dir_features, n_dot_d)
        specular = torch.sigmoid(self.rgb_head(hv))
        rgb = torch.clamp(linear_to_srgb(tint * specular + diffuse), 0.0, 1.0)
        rgb = rgb * (1 + 2 * self.rgb_padding) - self.rgb_padding
        return {
            "density": density,
            "rgb": rgb,
            **normals,
            "normals_pred": normals_pred,
            "diffuse": diffuse,
            "tint": tint,
            "specular": specular,
            "roughness": roughness[..., 0],
        }
