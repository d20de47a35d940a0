"""U-Net KPCN for the sequences' `radiance` branch (`dataset=volumetric`).

Zhu et al. 2023 (Pixar/Disney SIGGRAPH talk "Denoising Production Volumetric Rendering") reshape the
kernel-predicting network of Bako et al. 2017 / Vogels et al. 2018 into a U-Net with a kernel predictor at
every scale: "a considerably shallower design and faster inference", on log-modulus inputs
sign(x) log(1 + |x|). The multi-scale reconstruction is that of Vogels et al. 2018 ("Denoising with Kernel
Prediction and Asymmetric Loss Functions", Sec. 5):

1. Radiance pyramid: r_0 = the noisy radiance, r_{s+1} = D(r_s), D the 2x2 average (`downsample`).
2. At every scale s a k x k softmax kernel predicted from the U-Net's decoder features at that scale
   filters r_s (`apply_kernel`, Bako et al. 2017 Eq. 5-6): f_s = K_s * r_s.
3. Coarse to fine (`compose_scales`), starting from c_{S-1} = f_{S-1}:

       c_s = f_s - a_s * U(D(f_s)) + a_s * U(c_{s+1}),

   U the nearest 2x upsampling (`upsample`, D(U(c)) = c), a_s in [0, 1] per pixel from a small conv
   net on [U(c_{s+1}), f_s] (`ScaleCompositor`). a_s = 0 keeps the fine scale; a_s = 1 replaces the
   fine scale's low-frequency band U(D(f_s)) by the (less noisy) coarse result. The output is c_0.

Design choices (the YAML keys of `UNetKPCN`, `conf/model/unet_kpcn.yaml`):

- Encoder downsampling is the 2x2 average pool, not a strided convolution: no parameters or FLOPs (the
  budget goes to the convolutions at each scale), and it is the same D as the radiance pyramid, so the
  features at scale s describe exactly the pixels the kernel at scale s filters.
- `components: color` (default): one kernel head per scale filters the noisy colour. `surface_volume`:
  two heads per scale filter the noisy surface and volume radiance separately, the two results are
  summed. The default halves the kernel-application cost and needs no stored decomposition (a production
  render's storage budget argues against keeping it); the split is an ablation.
- `filter_space: linear` (default): kernels filter linear radiance (the inverse transform of
  `color_t`/`surface_t`/`volume_t`); softmax kernels and the composition are convex combinations, so
  the mean radiance is preserved (no Jensen bias from averaging in log space). `transformed` filters the
  transformed radiance and inverts the result (as Bako et al.'s KPCN does).
- The compositor sees [U(c), f] under `transform` (log-modulus by default) whatever the filter space:
  linear HDR radiance spans orders of magnitude and would be a badly conditioned input to a conv net.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import torch
import torch.nn.functional as F
from torch import nn

from src.data.sequence_dataset import RADIANCE_BRANCH
from src.data.transforms import VOLUME_TRANSFORMS, inverse_volume_transform, volume_transform
from src.errors import ConfigError
from src.models.denoise.base import Batch, Denoiser, branch_input
from src.models.denoise.kernels import apply_kernel, kernel_application_flops
from src.models.instantiate import at_least

Transform = Literal["log_modulus", "none"]
#: `components` -> the batch keys of the (transformed) radiance each kernel head filters.
COMPONENTS = {"color": (f"{RADIANCE_BRANCH}_t",), "surface_volume": ("surface_t", "volume_t")}
FILTER_SPACES = ("linear", "transformed")
#: Elementwise FLOPs per pixel (3 channels) of one composition step at the fine scale: D(f) (~1 per
#: channel per fine pixel), f - a*U(D f) + a*U(c) (4 per channel), and the sigmoid of a (~4).
COMPOSE_FLOPS = 3 * (1 + 4) + 4
#: Elementwise FLOPs per pixel of building one pyramid level (2x2 average: ~1 per channel per fine pixel).
PYRAMID_FLOPS = 3
RGB = 3


def downsample(x: torch.Tensor) -> torch.Tensor:
    """D: 2x2 average pooling, (N, C, H, W) -> (N, C, H/2, W/2) (H, W even). Vogels et al. 2018, Sec. 5."""
    return F.avg_pool2d(x, 2)


def upsample(x: torch.Tensor) -> torch.Tensor:
    """U: nearest 2x upsampling (each pixel repeated 2x2), the transpose-like "repeat" of `downsample`:
    D(U(c)) = c exactly."""
    return F.interpolate(x, scale_factor=2, mode="nearest")


def compose_scales(fine: torch.Tensor, coarse: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Vogels et al. 2018's scale composition: f - a * U(D(f)) + a * U(c).

    Args:
        fine: f, (N, C, H, W) the fine scale's filtered image (H, W even).
        coarse: c, (N, C, H/2, W/2) the composed result of the coarser scales.
        a: (N, 1, H, W) (or broadcastable) blending weight in [0, 1].

    a = 0 returns f; a = 1 swaps f's low-frequency band U(D(f)) for U(c). D(result) =
    (1 - a) D(f) + a c where a is constant over a 2x2 block.
    """
    return fine - a * upsample(downsample(fine)) + a * upsample(coarse)


def radiance_pyramid(x: torch.Tensor, scales: int) -> list[torch.Tensor]:
    """[x, D(x), D^2(x), ...], `scales` levels (H, W divisible by 2^(scales-1))."""
    levels = [x]
    for _ in range(scales - 1):
        levels.append(downsample(levels[-1]))
    return levels


def pad_to_multiple(x: torch.Tensor, multiple: int) -> torch.Tensor:
    """Replicate-pad the bottom and right of (N, C, H, W) up to multiples of `multiple`."""
    height, width = x.shape[-2:]
    dy, dx = -height % multiple, -width % multiple
    return F.pad(x, (0, dx, 0, dy), mode="replicate") if dy or dx else x


def _conv_block(c_in: int, c_out: int, convs: int, conv_kernel: int) -> nn.Sequential:
    """`convs` 'same' convolutions c_in -> c_out -> ... -> c_out, each followed by a ReLU."""
    layers: list[nn.Module] = []
    for i in range(convs):
        layers += [nn.Conv2d(c_in if i == 0 else c_out, c_out, conv_kernel, padding=conv_kernel // 2)]
        layers += [nn.ReLU(inplace=True)]
    return nn.Sequential(*layers)


class ScaleCompositor(nn.Module):
    """a = sigmoid(conv1x1(relu(conv_kxk([U(c), f])))): the per-pixel weight of `compose_scales`
    (one channel), from the upsampled coarse result and the fine scale's filtered image (3 + 3 channels,
    under the volume transform)."""

    def __init__(self, width: int, conv_kernel: int = 3, channels: int = RGB) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(2 * channels, width, conv_kernel, padding=conv_kernel // 2),
            nn.ReLU(inplace=True),
            nn.Conv2d(width, 1, 1),
        )
        self.radius = conv_kernel // 2

    def forward(self, coarse_up: torch.Tensor, fine: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(torch.cat([coarse_up, fine], dim=1)))


def _check_choice(key: str, value: str, choices: Sequence[str]) -> str:
    if value not in choices:
        raise ConfigError(f"model.{key}: expected one of {list(choices)}, got {value!r}")
    return value


def _check_widths(widths) -> list[int]:
    ok = isinstance(widths, Sequence) and not isinstance(widths, str) and len(widths) > 0
    if not ok or not all(isinstance(w, int) and not isinstance(w, bool) and w >= 1 for w in widths):
        raise ConfigError(
            f"model.widths: expected a non-empty list of positive integers (one per scale), got {widths!r}"
        )
    return list(widths)


class UNetKPCN(Denoiser):
    """U-Net kernel predictor with a softmax kernel at every scale and Vogels et al.'s coarse-to-fine
    composition (module docstring). Reads the `radiance` branch; returns {"color": linear (N, 3, H, W)}.

    Args (all from `conf/model/unet_kpcn.yaml`):
        in_channels: channels of batch["radiance_in"] (`dataset.volume_features`).
        widths: feature channels per scale; S = len(widths) scales (S - 1 2x2 poolings).
        convs_per_level: convolutions per encoder and decoder level.
        conv_kernel: their size (odd).
        kernel_size: k of the per-pixel kernels (odd), the same at every scale.
        compositor_width: hidden channels of each `ScaleCompositor`.
        components: "color" (one kernel head per scale) or "surface_volume" (two, results summed).
        filter_space: "linear" (filter the inverse-transformed radiance) or "transformed".
        transform: the batch's radiance transform (`dataset.preprocess.volume_transform`).

    Any H x W is accepted: the frame is replicate-padded to multiples of 2^(S-1) and cropped back.
    """

    branches = (RADIANCE_BRANCH,)

    def __init__(
        self,
        *,
        in_channels: int,
        widths: list[int],
        convs_per_level: int,
        conv_kernel: int,
        kernel_size: int,
        compositor_width: int,
        components: Literal["color", "surface_volume"],
        filter_space: Literal["linear", "transformed"],
        transform: Transform,
    ) -> None:
        super().__init__()
        self.in_channels = int(at_least("in_channels", in_channels))
        self.widths = _check_widths(widths)
        self.convs_per_level = int(at_least("convs_per_level", convs_per_level))
        self.conv_kernel = int(at_least("conv_kernel", conv_kernel, odd=True))
        self.kernel_size = int(at_least("kernel_size", kernel_size, odd=True))
        at_least("compositor_width", compositor_width)
        self.components = _check_choice("components", components, tuple(COMPONENTS))
        self.filter_space = _check_choice("filter_space", filter_space, FILTER_SPACES)
        self.transform = _check_choice("transform", transform, VOLUME_TRANSFORMS)
        self.keys = COMPONENTS[components]
        scales = len(self.widths)
        w = self.widths
        self.encoder = nn.ModuleList(
            _conv_block(in_channels if s == 0 else w[s - 1], w[s], convs_per_level, conv_kernel)
            for s in range(scales)
        )
        # decoder[s] for s < S-1: upsampled scale-s+1 features concatenated with the scale-s skip.
        self.decoder = nn.ModuleList(
            _conv_block(w[s + 1] + w[s], w[s], convs_per_level, conv_kernel) for s in range(scales - 1)
        )
        taps = self.kernel_size**2
        # One 1x1 head per scale: k*k kernel scores per component.
        self.heads = nn.ModuleList(nn.Conv2d(w[s], len(self.keys) * taps, 1) for s in range(scales))
        # compositors[component][s] blends scale s with the composed scales s+1.. (s < S-1).
        self.compositors = nn.ModuleList(
            nn.ModuleList(ScaleCompositor(compositor_width) for _ in range(scales - 1)) for _ in self.keys
        )

    @property
    def scales(self) -> int:
        return len(self.widths)

    @property
    def size_multiple(self) -> int:
        """Frames are processed padded to multiples of this (2^(S-1)); tiles should be multiples too."""
        return 2 ** (self.scales - 1)

    @property
    def halo(self) -> int:
        """An upper bound of the receptive-field radius in full-resolution pixels, rounded up to a multiple
        of 2^(S-1) (so that `infer_tiled` pieces stay on the pooling grid when tiles are multiples of it).

        Every dependency path of an output pixel is a subset of these operations, each adding its radius
        at its scale s (x 2^s): the encoder convs and poolings, the decoder upsamplings and convs (1x1
        heads add nothing), at every scale the pyramid's D, the kernel (k//2) and, for s < S-1, the
        compositor conv and the U of the composition.
        """
        r, c, scales = self.conv_kernel // 2, self.convs_per_level, self.scales
        radius = 0
        for s in range(scales):
            step = 2**s
            radius += c * r * step + step  # encoder convs; pooling into / pyramid level s
            radius += (self.kernel_size // 2) * step  # kernel at scale s
            if s < scales - 1:
                radius += c * r * step + step  # decoder convs; upsampling from s+1
                radius += (1 + 1) * step  # compositor conv (3x3) and U(D f) / U(c)
        multiple = self.size_multiple
        return -(-radius // multiple) * multiple

    def compositor_modules(self) -> nn.Module:
        return self.compositors

    def kernel_flops_per_pixel(self) -> float:
        """FLOPs per output pixel outside the convolutions: the kernel application at every scale weighted
        by its pixel fraction 4^-s, the radiance pyramid and the elementwise composition, per component."""
        per_component = 0.0
        for s in range(self.scales):
            fraction = 4.0**-s
            per_component += kernel_application_flops(self.kernel_size) * fraction
            if s > 0:
                per_component += PYRAMID_FLOPS * 4.0 ** -(s - 1)
            if s < self.scales - 1:
                per_component += COMPOSE_FLOPS * fraction
        return len(self.keys) * per_component

    def kernel_logits(self, x: torch.Tensor) -> list[torch.Tensor]:
        """The U-Net on padded inputs (N, C, H, W): per scale s the (N, components*k*k, H/2^s, W/2^s)
        kernel scores."""
        skips: list[torch.Tensor] = []
        h = x
        for s, block in enumerate(self.encoder):
            h = block(h if s == 0 else downsample(h))
            skips.append(h)
        features = [h] * self.scales
        for s in reversed(range(self.scales - 1)):
            h = self.decoder[s](torch.cat([upsample(h), skips[s]], dim=1))
            features[s] = h
        return [head(f) for head, f in zip(self.heads, features, strict=True)]

    def filter_scales(self, logits: list[torch.Tensor], radiance: torch.Tensor, component: int = 0):
        """f_s = K_s * D^s(radiance) for every scale s: the `component`-th kernel of each scale's scores
        (`kernel_logits`) applied to the radiance pyramid (padded frame)."""
        taps = self.kernel_size**2
        pyramid = radiance_pyramid(radiance, self.scales)
        return [
            apply_kernel(scores[:, component * taps : (component + 1) * taps], level, self.kernel_size)
            for scores, level in zip(logits, pyramid, strict=True)
        ]

    def _compose(self, filtered: list[torch.Tensor], compositors: nn.ModuleList) -> torch.Tensor:
        """c_0 from the filtered pyramid f_0..f_{S-1}, coarse to fine (`compose_scales`)."""
        to_net = (
            (lambda t: t)
            if self.filter_space == "transformed"
            else (lambda t: volume_transform(t, self.transform))
        )
        composed = filtered[-1]
        for s in reversed(range(self.scales - 1)):
            a = compositors[s](to_net(upsample(composed)), to_net(filtered[s]))
            composed = compose_scales(filtered[s], composed, a)
        return composed

    def forward(self, batch: Batch) -> dict[str, torch.Tensor]:
        x = branch_input(batch, RADIANCE_BRANCH, self.in_channels)
        height, width = x.shape[-2:]
        multiple = self.size_multiple
        logits = self.kernel_logits(pad_to_multiple(x, multiple))
        color = None
        for i, key in enumerate(self.keys):
            radiance = pad_to_multiple(batch[key], multiple)
            if self.filter_space == "linear":
                radiance = inverse_volume_transform(radiance, self.transform)
            filtered = self.filter_scales(logits, radiance, i)
            part = self._compose(filtered, self.compositors[i])
            if self.filter_space == "transformed":
                part = inverse_volume_transform(part, self.transform)
            color = part if color is None else color + part
        return {"color": color[..., :height, :width]}
