"""The sRGB transfer curve (IEC 61966-2-1): 12.92 x for x <= 0.0031308, else 1.055 x^(1/2.4) - 0.055.

One home for its two forms, kept apart on purpose because each must match its own reference bit for bit:
- `srgb_oetf` (numpy, the standard's constants): encoding rendered linear images to 8-bit PNGs, as
  Blender writes its sRGB PNGs (the multi-view renderer's output);
- `linear_to_srgb` (torch, differentiable): Ref-NeRF's tone mapping, written as multinerf writes it
  (323/25 x and (211 x^(5/12) - 11) / 200, with x clamped at eps below the power so its gradient stays
  finite at 0), so that the model equals multinerf to float precision.
"""

import numpy as np
import torch
from torch import Tensor


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) of linear values in [0, 1]."""
    linear = np.asarray(linear)
    return np.where(
        linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(np.maximum(linear, 0.0031308), 1 / 2.4) - 0.055
    )


def linear_to_srgb(linear: Tensor, eps: float = torch.finfo(torch.float32).eps) -> Tensor:
    """The sRGB transfer curve, Ref-NeRF's tone mapping (Sec. 3), in multinerf's form (see the module)."""
    srgb0 = 323 / 25 * linear
    srgb1 = (211 * torch.clamp(linear, min=eps) ** (5 / 12) - 11) / 200
    return torch.where(linear <= 0.0031308, srgb0, srgb1)
