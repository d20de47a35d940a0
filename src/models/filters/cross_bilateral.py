"""Cross-bilateral filter with constant feature sigmas: the non-learned baseline of the seed thesis on
filter weight expressions (`conf/model/cross_bilateral.yaml`).

For an output pixel p and each q in the (2r+1) x (2r+1) window around it (Tomasi & Manduchi 1998,
joint/cross form as in Eisemann & Durand 2004, with the auxiliary G-buffers of MC denoising):

    w(p, q) = exp( - |p - q|^2     / (2 s_spatial^2)
                   - |c'_p - c'_q|^2 / (2 s_color^2)
                   - |n_p - n_q|^2   / (2 s_normal^2)
                   - |a_p - a_q|^2   / (2 s_albedo^2)
                   - (z_p - z_q)^2   / (2 s_depth^2) )

    out_p = sum_q w(p, q) c_q / sum_q w(p, q)

Conventions:
- |.|^2 is the squared Euclidean distance, i.e. squared differences *summed over channels* (3 for
  colour, normal and albedo, 1 for depth); |p - q| is in pixels.
- c' = log(1 + max(c, 0)) compresses the high dynamic range of the noisy colour for the *distance*
  only (fireflies would otherwise get zero weight from every neighbour and stay); the filtered *value*
  c_q is the linear HDR colour, so the output is linear HDR as the Denoiser interface requires.
- Borders use replicate padding (a window that leaves the image sees the edge pixel repeated).
- The centre pixel always has weight exp(0) = 1, so the normalisation never divides by zero.

Implementation: one pass per window offset (slice the padded buffers, exp, multiply-add), so memory stays
O(N*C*H*W) whatever the radius (no `unfold` into a (2r+1)^2-times larger tensor, no loop over pixels).
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import torch
import torch.nn.functional as F

from src.errors import ConfigError
from src.models.denoise.base import Batch, Denoiser

#: Guide buffers (batch key, channel count) besides the compressed colour, in guide channel order.
FEATURE_BUFFERS = (("normal", 3), ("albedo", 3), ("depth", 1))
#: Guide channels: compressed colour (3) + normal (3) + albedo (3) + depth (1).
GUIDE_CHANNELS = 3 + sum(c for _, c in FEATURE_BUFFERS)


def _scaled(x: torch.Tensor, sigma: float) -> torch.Tensor:
    """x / (sqrt(2) sigma), so that a squared difference of scaled values is |d|^2 / (2 sigma^2)."""
    return x / (math.sqrt(2.0) * sigma)


def guide_features(
    color: torch.Tensor,
    normal: torch.Tensor,
    albedo: torch.Tensor,
    depth: torch.Tensor,
    sigmas: Mapping[str, float],
) -> torch.Tensor:
    """(N, 10, H, W) guide: [log(1 + max(c, 0)), n, a, z], each divided by sqrt(2) times its sigma.

    With this scaling the feature part of the exponent is just the channel-summed squared difference of
    two guide vectors (an infinite sigma gives a zero channel: that feature is ignored).
    """
    parts = [_scaled(torch.log1p(color.clamp(min=0.0)), sigmas["color"])]
    for (name, _), x in zip(FEATURE_BUFFERS, (normal, albedo, depth), strict=True):
        parts.append(_scaled(x, sigmas[name]))
    return torch.cat(parts, dim=1)


def cross_bilateral(
    color: torch.Tensor, guide: torch.Tensor, radius: int, sigma_spatial: float
) -> torch.Tensor:
    """Filter linear `color` (N, C, H, W) with weights from a pre-scaled `guide` (see `guide_features`)
    and a spatial Gaussian of `sigma_spatial` pixels over a (2r+1)^2 window (module docstring equation).
    """
    n, c, h, w = color.shape
    pad = (radius, radius, radius, radius)
    color_pad = F.pad(color, pad, mode="replicate")
    guide_pad = F.pad(guide, pad, mode="replicate")
    acc = torch.zeros_like(color)
    weight_sum = torch.zeros((n, 1, h, w), dtype=color.dtype, device=color.device)
    # Buffers reused by every offset: allocating fresh full-frame temporaries per offset made the CPU
    # version ~8x slower (page faults), and memory stays a few frames whatever the radius.
    diff = torch.empty_like(guide)
    weight = torch.empty_like(weight_sum)
    for dy in range(2 * radius + 1):
        for dx in range(2 * radius + 1):
            spatial = ((dy - radius) ** 2 + (dx - radius) ** 2) / (2.0 * sigma_spatial**2)
            torch.sub(guide_pad[:, :, dy : dy + h, dx : dx + w], guide, out=diff)
            torch.sum(diff.square_(), dim=1, keepdim=True, out=weight)
            weight.add_(spatial).neg_().exp_()  # w = exp(-(feature term + spatial term))
            acc.addcmul_(weight, color_pad[:, :, dy : dy + h, dx : dx + w])
            weight_sum.add_(weight)
    return acc / weight_sum


class CrossBilateralFilter(Denoiser):
    """Cross-bilateral filter on linear HDR colour guided by normal, albedo and depth (constant sigmas).

    Reads batch["color"] (N, 3, H, W), batch["normal"] (3), batch["albedo"] (3), batch["depth"] (1);
    returns {"color": filtered linear HDR colour}. No parameters are trained (`learned = False`).
    """

    learned = False

    def __init__(
        self,
        radius: int,
        sigma_spatial: float,
        sigma_color: float,
        sigma_normal: float,
        sigma_albedo: float,
        sigma_depth: float,
    ) -> None:
        super().__init__()
        if int(radius) != radius or radius < 0:
            raise ConfigError(f"model.radius must be an integer >= 0, got {radius!r}")
        sigmas = {
            "spatial": sigma_spatial,
            "color": sigma_color,
            "normal": sigma_normal,
            "albedo": sigma_albedo,
            "depth": sigma_depth,
        }
        for name, value in sigmas.items():
            # A zero sigma would divide by zero; float("inf") is allowed and switches a feature off.
            if not float(value) > 0.0:
                raise ConfigError(f"model.sigma_{name} must be > 0, got {value!r}")
        self.radius = int(radius)
        self.sigmas = {k: float(v) for k, v in sigmas.items()}

    @property
    def halo(self) -> int:
        """An output pixel depends on inputs up to `radius` pixels away."""
        return self.radius

    def flops_per_pixel(self) -> int:
        """Estimated floating-point operations per output pixel.

        Per window offset: guide difference and square (2 * 10), channel sum (9), spatial term (1),
        exp counted as 1, colour multiply-add (2 * 3), weight sum (1) = 3 * 10 + 8 = 38.
        Per pixel once: guide (3 log1p + 10 scalings) and normalisation (3 divisions) = 16.
        Total 38 * (2r+1)^2 + 16 (16774 for r = 10); padding and memory traffic are not counted.
        """
        per_offset = 3 * GUIDE_CHANNELS + 8
        per_pixel = 3 + GUIDE_CHANNELS + 3
        return per_offset * (2 * self.radius + 1) ** 2 + per_pixel

    @torch.no_grad()
    def forward(self, batch: Batch) -> dict[str, torch.Tensor]:
        color = batch["color"].float()
        guide = guide_features(
            color, batch["normal"].float(), batch["albedo"].float(), batch["depth"].float(), self.sigmas
        )
        return {"color": cross_bilateral(color, guide, self.radius, self.sigmas["spatial"])}
