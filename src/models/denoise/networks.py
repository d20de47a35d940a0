"""The convolutional backbones of the learned denoisers. Every size comes from the model config.

- `ConvStack`: the DPCN/KPCN network of Bako et al. 2017 (Sec. 4.2): `depth` 'same'-padded convolutions
  of `width` channels with ReLU between them; the last layer outputs 3 colour channels (DPCN) or k*k kernel
  scores (KPCN).
- `ResidualKernelNet`: the residual kernel predictor in the style of Vogels et al. 2018 ("Denoising with
  Kernel Prediction and Asymmetric Loss Functions", Sec. 4: source encoder + residual blocks + kernel
  predictor), as in the seed thesis: two-conv encoder, pre-activation residual blocks, 1x1 predictor.

Each network exposes `halo`: its receptive-field radius in pixels (what tiled inference pads tiles by).
"""

from __future__ import annotations

import torch
from torch import nn


def _same_conv(in_channels: int, out_channels: int, kernel: int) -> nn.Conv2d:
    """Stride-1 convolution with zero padding that keeps H x W (odd kernels only)."""
    if kernel < 1 or kernel % 2 == 0:
        raise ValueError(f"conv kernel must be a positive odd integer, got {kernel}")
    return nn.Conv2d(in_channels, out_channels, kernel, padding=kernel // 2)


class ConvStack(nn.Sequential):
    """`depth` convolutions (k x k, zero 'same' padding), ReLU after all but the last (Bako et al. 2017).

    Paper sizes (28 -> 100 x 8 -> out, 5x5): 1,828,303 parameters with 3 outputs (DPCN), 2,923,741 with
    441 outputs (KPCN, 21x21 kernel).
    """

    def __init__(self, in_channels: int, width: int, depth: int, conv_kernel: int, out_channels: int) -> None:
        if depth < 1:
            raise ValueError(f"depth must be >= 1, got {depth}")
        sizes = [in_channels] + [width] * (depth - 1) + [out_channels]
        layers: list[nn.Module] = []
        for layer, (c_in, c_out) in enumerate(zip(sizes[:-1], sizes[1:], strict=True)):
            layers.append(_same_conv(c_in, c_out, conv_kernel))
            if layer < depth - 1:
                layers.append(nn.ReLU(inplace=True))
        super().__init__(*layers)
        self.depth = depth
        self.conv_kernel = conv_kernel

    @property
    def halo(self) -> int:
        """Receptive-field radius: each conv layer adds k//2 pixels."""
        return self.depth * (self.conv_kernel // 2)


class ResidualBlock(nn.Module):
    """Pre-activation residual block: x + conv(relu(conv(relu(x)))) (He et al. 2016; Vogels et al. 2018)."""

    def __init__(self, width: int, conv_kernel: int) -> None:
        super().__init__()
        self.conv1 = _same_conv(width, width, conv_kernel)
        self.conv2 = _same_conv(width, width, conv_kernel)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # Not in-place: x is still needed for the skip connection.
        return x + self.conv2(torch.relu(self.conv1(torch.relu(x))))


class ResidualKernelNet(nn.Module):
    """Encoder (two k x k convs + ReLU), `blocks` pre-activation residual blocks, 1x1 predictor
    (width -> predictor_width -> ReLU -> out_channels). Vogels et al. 2018 style, seed thesis sizes:
    28/64/12 blocks/3x3/64/441 -> 972,217 parameters.
    """

    def __init__(
        self,
        in_channels: int,
        width: int,
        blocks: int,
        conv_kernel: int,
        predictor_width: int,
        out_channels: int,
    ) -> None:
        super().__init__()
        if blocks < 0:
            raise ValueError(f"blocks must be >= 0, got {blocks}")
        self.encoder = nn.Sequential(
            _same_conv(in_channels, width, conv_kernel),
            nn.ReLU(inplace=True),
            _same_conv(width, width, conv_kernel),
            nn.ReLU(inplace=True),
        )
        self.blocks = nn.Sequential(*(ResidualBlock(width, conv_kernel) for _ in range(blocks)))
        # 1x1 convs: the predictor mixes channels per pixel and does not widen the receptive field.
        self.predictor = nn.Sequential(
            nn.Conv2d(width, predictor_width, 1),
            nn.ReLU(inplace=True),
            nn.Conv2d(predictor_width, out_channels, 1),
        )
        self.num_blocks = blocks
        self.conv_kernel = conv_kernel

    @property
    def halo(self) -> int:
        """2 encoder convs + 2 convs per block, k//2 pixels each; the 1x1 predictor adds nothing."""
        return (2 + 2 * self.num_blocks) * (self.conv_kernel // 2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.predictor(self.blocks(self.encoder(x)))
