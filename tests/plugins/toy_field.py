"""A radiance field from outside `src/`, as a user would write one (docs/extending.md): a
`NerfModelBase` subclass whose field is a small MLP of the raw sample position (no encoding, no view
dependence), one MLP for both levels. Config: `tests/conf/model/toy_field.yaml`."""

import torch.nn.functional as F
from torch import nn

from src.models.nerf.models import NerfModelBase


class ToyField(NerfModelBase):
    name = "toy_field"

    def __init__(
        self, *, hidden: int, num_coarse_samples: int, num_fine_samples: int, background: list
    ) -> None:
        mlp = nn.Sequential(nn.Linear(3, hidden), nn.ReLU(), nn.Linear(hidden, 4))
        super().__init__(
            mlp,
            None,
            num_coarse_samples=num_coarse_samples,
            num_fine_samples=num_fine_samples,
            resample_padding=0.01,  # mip-NeRF-style resampling of the coarse weights
            background=background,
        )

    def evaluate(self, level, rays, tdist):
        t_mid = 0.5 * (tdist[..., 1:] + tdist[..., :-1])
        x = rays["origins"][..., None, :] + t_mid[..., None] * rays["directions"][..., None, :]
        out = self.mlp_for(level)(x)
        return {"density": F.softplus(out[..., 0] - 1.0), "rgb": out[..., 1:].sigmoid()}
