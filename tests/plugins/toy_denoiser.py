"""A denoiser from outside `src/`, as a user would write one (README, "Add your own method"): per branch,
a two-layer 1x1-convolution network from the 28 KPCN inputs to the transformed colour. Its config is
`tests/conf/model/toy.yaml`; the tests run it through training, evaluation, the report and a multirun
without any edit under `src/`."""

from torch import nn

from src.models.denoise.base import Denoiser


class ToyDenoiser(Denoiser):
    learned = True

    def __init__(self, in_channels: int, hidden: int) -> None:
        super().__init__()
        self.nets = nn.ModuleDict(
            {
                branch: nn.Sequential(nn.Conv2d(in_channels, hidden, 1), nn.ReLU(), nn.Conv2d(hidden, 3, 1))
                for branch in ("diffuse", "specular")
            }
        )

    @property
    def halo(self) -> int:
        return 0  # 1x1 convolutions: an output pixel sees only its own inputs

    def forward(self, batch):
        return {branch: net(batch[f"{branch}_in"]) for branch, net in self.nets.items()}
