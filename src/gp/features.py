"""Feature preparation for weight expressions: the thesis's normalisation and Sobel gradients.

Davletaliyev 2016, Sec. 3.3.2: "All of the feature values including the gradients are normalized. One
dimensional feature values were mapped to the interval between [0, 1] by dividing all values by the maximum
value in the scene. Three dimensional feature values were normalized by dividing component-wise each value of
the feature by the length of the biggest vector." Gradients are "computed ... by Sobol [Sobel] operator"
(Sec. 3.2.1.2); the thesis shows them as images (Fig. 3.3), one value per channel, which we read as the
per-channel Sobel gradient magnitude sqrt(gx^2 + gy^2) (a 3-channel feature keeps 3 channels).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

_SOBEL_X = torch.tensor([[-1.0, 0.0, 1.0], [-2.0, 0.0, 2.0], [-1.0, 0.0, 1.0]])


def normalization_scale(x: torch.Tensor) -> torch.Tensor:
    """(N, 1, 1, 1) divisor of `normalize_feature`: per image, max |x| for a 1-channel feature (the maximum
    for the non-negative features the thesis has), the largest per-pixel Euclidean length otherwise; 1 where
    that is 0 (an all-zero feature stays zero)."""
    length = x.abs() if x.shape[1] == 1 else x.square().sum(1, keepdim=True).sqrt()
    scale = length.flatten(1).amax(1)
    return torch.where(scale > 0, scale, torch.ones_like(scale)).view(-1, 1, 1, 1)


def normalize_feature(x: torch.Tensor) -> torch.Tensor:
    """(N, C, H, W) feature normalised as the thesis does (module docstring), per image."""
    return x / normalization_scale(x)


def sobel_gradient(x: torch.Tensor) -> torch.Tensor:
    """Per-channel Sobel gradient magnitude of (N, C, H, W) `x` (replicate borders), (N, C, H, W)."""
    c = x.shape[1]
    kx = _SOBEL_X.to(x).view(1, 1, 3, 3).expand(c, 1, 3, 3)
    ky = _SOBEL_X.t().to(x).reshape(1, 1, 3, 3).expand(c, 1, 3, 3)
    padded = F.pad(x, (1, 1, 1, 1), mode="replicate")
    gx = F.conv2d(padded, kx, groups=c)
    gy = F.conv2d(padded, ky, groups=c)
    return (gx.square() + gy.square()).sqrt()
