"""LPIPS (Zhang et al. 2018, "The Unreasonable Effectiveness of Deep Features as a Perceptual Metric") on
torchvision's VGG16, without the `lpips` package or any download.

Eq. 1 of the paper: d(x, y) = sum_l 1 / (H_l W_l) sum_{h,w} || w_l * (yhat^l_hw(x) - yhat^l_hw(y)) ||_2^2,
where yhat^l are the trunk activations of layer l unit-normalised over channels and w_l are per-channel
linear weights (a 1x1 convolution without bias). Layers l are VGG16's relu1_2, relu2_2, relu3_3, relu4_3
and relu5_3 (indices 3, 8, 15, 22, 29 of `torchvision.models.vgg16().features`). Inputs first go through
LPIPS' scaling layer (x - shift) / scale with shift = (-.030, -.088, -.188), scale = (.458, .448, .450).

Inputs MUST be RGB in [-1, 1] (N, 3, H, W); feeding [0, 1] silently gives wrong numbers (see
`lpips_distance` for numpy images in [0, 1]).

Variants (recorded with every number, see `LPIPS.variant`):
- trunk: `trunk_weights=None` is a deterministic, seeded random init (pretrained ImageNet weights cannot
  be downloaded here); otherwise a torchvision VGG16 state dict file (full model keys `features.N.*` or a
  features-only dict with keys `N.*`).
- linear weights: `lin_weights=None` is the "baseline" of the `lpips` package (`lpips=False`): the squared
  difference summed over channels, i.e. weight 1 per channel; otherwise the official v0.1 file
  (`lin0.model.1.weight` .. `lin4.model.1.weight`, shapes (1, C_l, 1, 1)).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
import torchvision
from torch import nn

from src.errors import ConfigError, DataError

#: VGG16 halves the resolution 4 times before relu5_3.
MIN_SIZE = 16
#: Indices in `vgg16().features` of the ReLUs after conv1_2, conv2_2, conv3_3, conv4_3, conv5_3.
TAPS = (3, 8, 15, 22, 29)
CHANNELS = (64, 128, 256, 512, 512)
SHIFT = (-0.030, -0.088, -0.188)
SCALE = (0.458, 0.448, 0.450)
EPS = 1e-10


def _load(path: str | Path, key: str) -> dict[str, torch.Tensor]:
    try:
        state = torch.load(Path(path), map_location="cpu", weights_only=True)
    except Exception as exc:  # missing file, not a torch file, pickled objects...
        msg = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ConfigError(f"{key}={str(path)!r}: cannot load a state dict ({msg})") from None
    if isinstance(state, dict) and isinstance(state.get("state_dict"), dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ConfigError(f"{key}={str(path)!r}: expected a state dict, found {type(state).__name__}")
    return state


def _features_state(state: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """`features.N.*` keys (full torchvision model) or `N.*` keys (features only) -> `N.*`."""
    if any(k.startswith("features.") for k in state):
        return {k[len("features.") :]: v for k, v in state.items() if k.startswith("features.")}
    return dict(state)


def _vgg16_features() -> nn.Sequential:
    """`torchvision.models.vgg16(weights=None).features` up to relu5_3 (the last max-pool is unused)."""
    return torchvision.models.vgg16(weights=None).features[: TAPS[-1] + 1]


def _trunk(trunk_weights: str | Path | None, seed: int) -> tuple[nn.Sequential, str]:
    """The trunk and its variant name: seeded random init (global RNG untouched) or loaded from a file."""
    if trunk_weights is None:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            return _vgg16_features(), f"vgg16-random(seed={seed})"
    key = "metrics.lpips.trunk_weights"
    state = _features_state(_load(trunk_weights, key))
    with torch.device("meta"):  # shapes only: no 138M-parameter random init for weights that get replaced
        features = _vgg16_features()
    expected = features.state_dict()
    missing = sorted(set(expected) - set(state), key=lambda k: int(k.split(".")[0]))
    if missing:
        raise ConfigError(
            f"{key}={str(trunk_weights)!r}: not a torchvision VGG16 state dict "
            f"(missing {', '.join(missing[:3])}{', ...' if len(missing) > 3 else ''})"
        )
    for k, v in expected.items():
        if not isinstance(state[k], torch.Tensor) or tuple(state[k].shape) != tuple(v.shape):
            raise ConfigError(
                f"{key}={str(trunk_weights)!r}: {k} has shape {tuple(getattr(state[k], 'shape', ()))}, "
                f"expected {tuple(v.shape)}"
            )
    features = features.to_empty(device="cpu")
    features.load_state_dict({k: state[k].float() for k in expected})
    return features, f"vgg16-file({Path(trunk_weights).name})"


def _lin_weights(lin_weights: str | Path | None) -> tuple[list[torch.Tensor], str]:
    """Per-layer (1, C_l, 1, 1) weights and their variant name: 1 per channel, or the v0.1 file."""
    if lin_weights is None:
        return [torch.ones(1, c, 1, 1) for c in CHANNELS], "lin-uniform"
    key = "metrics.lpips.lin_weights"
    state = _load(lin_weights, key)
    weights = []
    for i, c in enumerate(CHANNELS):
        name = f"lin{i}.model.1.weight"
        w = state.get(name)
        if not isinstance(w, torch.Tensor) or tuple(w.shape) != (1, c, 1, 1):
            found = "missing" if w is None else f"shape {tuple(getattr(w, 'shape', ()))}"
            raise ConfigError(f"{key}={str(lin_weights)!r}: {name} is {found}, expected shape (1, {c}, 1, 1)")
        weights.append(w.detach().float().clone())
    return weights, f"lin-v0.1({Path(lin_weights).name})"


class LPIPS(nn.Module):
    """LPIPS distance (Zhang et al. 2018, Eq. 1) with a frozen torchvision VGG16 trunk.

    forward(x, y): two (N, 3, H, W) tensors in [-1, 1] -> (N,) distances (0 for identical images).
    """

    def __init__(
        self, trunk_weights: str | Path | None = None, lin_weights: str | Path | None = None, seed: int = 0
    ) -> None:
        super().__init__()
        weights, lin = _lin_weights(lin_weights)  # checked first: cheap, and fails before the trunk is built
        self.features, trunk = _trunk(trunk_weights, int(seed))
        self.register_buffer("shift", torch.tensor(SHIFT)[None, :, None, None])
        self.register_buffer("scale", torch.tensor(SCALE)[None, :, None, None])
        for i, w in enumerate(weights):
            self.register_buffer(f"lin{i}", w)
        self._variant = f"{trunk}+{lin}"
        for p in self.parameters():
            p.requires_grad_(False)
        self.eval()

    @property
    def variant(self) -> str:
        """Which trunk and linear weights, e.g. "vgg16-random(seed=0)+lin-uniform"."""
        return self._variant

    def train(self, mode: bool = True) -> LPIPS:
        """Always in eval mode (frozen metric network)."""
        return super().train(False)

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out = []
        h = (x - self.shift) / self.scale
        for i, layer in enumerate(self.features):
            h = layer(h)
            if i in TAPS:
                out.append(h)
        return out

    def forward(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        """(N, 3, H, W) x 2 in [-1, 1] -> (N,) LPIPS distances."""
        if x.shape != y.shape or x.ndim != 4 or x.shape[1] != 3:
            raise ValueError(
                f"LPIPS: expected two (N, 3, H, W) tensors, got {tuple(x.shape)}, {tuple(y.shape)}"
            )
        total = x.new_zeros(x.shape[0])
        for i, (fx, fy) in enumerate(zip(self._taps(x), self._taps(y), strict=True)):
            nx = fx / (torch.sqrt(torch.sum(fx**2, dim=1, keepdim=True)) + EPS)
            ny = fy / (torch.sqrt(torch.sum(fy**2, dim=1, keepdim=True)) + EPS)
            d = ((nx - ny) ** 2 * getattr(self, f"lin{i}")).sum(dim=1)  # 1x1 conv, no bias
            total = total + d.mean(dim=(1, 2))
        return total


@torch.no_grad()
def lpips_distance(model: LPIPS, x_ldr_hwc: np.ndarray, y_ldr_hwc: np.ndarray) -> float:
    """LPIPS of two tone-mapped (H, W, 3) numpy images in [0, 1], mapped to [-1, 1] (2 v - 1) and
    computed in float32 on the model's device."""
    if min(np.shape(x_ldr_hwc)[:2]) < MIN_SIZE:
        raise DataError(
            f"lpips: image {np.shape(x_ldr_hwc)[0]}x{np.shape(x_ldr_hwc)[1]} is smaller than "
            f"{MIN_SIZE} pixels, too small for VGG16's relu5_3"
        )
    param = next(model.parameters())

    def to_tensor(a: np.ndarray) -> torch.Tensor:
        t = torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32)).permute(2, 0, 1)[None]
        return (t * 2.0 - 1.0).to(param.device)

    return float(model(to_tensor(x_ldr_hwc), to_tensor(y_ldr_hwc))[0])
