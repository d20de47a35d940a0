"""A denoiser from outside `src/`, as a user would write one (docs/extending.md): per branch of
the data (still images: diffuse and specular; sequences: radiance), a two-layer 1x1-convolution network
from the branch's inputs to its transformed colour. Its config is `tests/conf/model/toy.yaml`; the tests
run it through training, evaluation, the report and a multirun, on still images and on a toy kind of
sequences (`tests/plugins/toy_kind.py`), without any edit under `src/`."""

import torch
from torch import nn

from src.models.denoise.base import Denoiser


class ToyDenoiser(Denoiser):
    learned = True

    def __init__(self, in_channels: int, hidden: int, branches: list[str]) -> None:
        super().__init__()
        self.branches = tuple(branches)
        self.nets = nn.ModuleDict(
            {
                branch: nn.Sequential(nn.Conv2d(in_channels, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, 3, 1))
                for branch in self.branches
            }
        )

    @property
    def halo(self) -> int:
        return 0  # 1x1 convolutions: an output pixel sees only its own inputs

    def forward(self, batch):
        return {branch: net(batch[f"{branch}_in"]) for branch, net in self.nets.items()}


class ToyColorDenoiser(Denoiser):
    """One branch, predicting linear colour directly (no diffuse/specular pair): the noisy colour plus
    a per-pixel correction from the configured features. Config: `tests/conf/model/toy_color.yaml`.
    It reads the still images' diffuse inputs, so a kind of data without them refuses it in one line."""

    learned = True
    branches = ("diffuse",)

    def __init__(self, in_channels: int, hidden: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Conv2d(in_channels + 3, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, 3, 1))

    @property
    def halo(self) -> int:
        return 0

    def forward(self, batch):
        return {"color": batch["color"] + self.net(torch.cat([batch["color"], batch["diffuse_in"]], dim=1))}


class ToyBoxFilter(Denoiser):
    """A non-learned filter: the mean of the noisy colour over a (2r+1)^2 window (zero-padded borders,
    renormalised). Config: `tests/conf/model/toy_filter.yaml`; nothing to train, evaluated like the rest."""

    learned = False

    def __init__(self, radius: int) -> None:
        super().__init__()
        self.radius = radius

    @property
    def halo(self) -> int:
        return self.radius

    def forward(self, batch):
        size = 2 * self.radius + 1
        color = batch["color"]
        ones = torch.ones_like(color[:, :1])
        total = torch.nn.functional.avg_pool2d(
            color, size, stride=1, padding=self.radius, count_include_pad=True
        )
        weight = torch.nn.functional.avg_pool2d(
            ones, size, stride=1, padding=self.radius, count_include_pad=True
        )
        return {"color": total / weight}
