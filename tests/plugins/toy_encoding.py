"""An encoding from outside `src/`, as a user would write one (docs/radiance-fields.md): random
Fourier features (Tancik et al. 2020, "Fourier Features Let Networks Learn High Frequency Functions in Low
Dimensional Domains", Sec. 4, Gaussian mapping): gamma(x) = [cos(2 pi B x), sin(2 pi B x)] with the
rows of B (num_features x 3) drawn from N(0, scale^2 I) with `seed`. Its config,
`tests/conf/model/toy_encoding_nerf.yaml`, is NeRF's with this as the position encoding."""

import math

import torch
from torch import Tensor

from src.models.nerf.encodings import Encoding


class RandomFourierFeatures(Encoding):
    reads = "point"  # the interval midpoints, as NeRF's positional encoding

    def __init__(self, num_features: int, scale: float, seed: int = 0) -> None:
        super().__init__()
        if num_features < 1:
            raise ValueError(f"num_features: expected >= 1, got {num_features}")
        generator = torch.Generator().manual_seed(seed)
        # A buffer: saved in checkpoints and moved with the model (`.to(device)`).
        self.register_buffer("freqs", scale * torch.randn(num_features, self.in_dim, generator=generator))
        self.out_dim = 2 * num_features

    def forward(self, x: Tensor) -> Tensor:
        proj = 2 * math.pi * x @ self.freqs.to(x.dtype).T
        return torch.cat([torch.cos(proj), torch.sin(proj)], dim=-1)
