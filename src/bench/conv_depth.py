"""How deep a denoiser is: the number of convolution layers on its longest input-to-output path.

Issue 33 asks whether the U-Net KPCN of Zhu et al. 2023 ("a considerably shallower design") is shallower
than Bako et al. 2017's KPCN (9 conv layers per branch) or only narrower (16-64 channels against 100). A
U-Net's depth is not a config key: the longest path runs down the encoder, up the decoder and through a
kernel head and the scale compositors. `conv_depth` measures it by running the model once on a small
random batch with every tensor tagged by the most convolutions any path to it has passed through.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch
import torch.nn.functional as F
from torch.overrides import TorchFunctionMode
from torch.utils._pytree import tree_flatten
from torch.utils.weak import WeakTensorKeyDictionary

from src.models.denoise.base import Denoiser
from src.models.denoise.models import BRANCHES
from src.models.denoise.summary import random_batch

#: The functions that count as a convolution layer (nn.Conv2d calls F.conv2d).
CONVOLUTIONS = {F.conv1d, F.conv2d, F.conv3d, F.conv_transpose1d, F.conv_transpose2d, F.conv_transpose3d}
#: Side of the probe batch: a multiple of every U-Net's 2^(S-1) in conf/ (S <= 4), small enough to be quick.
PROBE_SIDE = 16


class _DepthMode(TorchFunctionMode):
    """Tags every tensor a torch function returns with 1 + (the largest tag of its tensor arguments) for a
    convolution, else that largest tag (inputs: 0). In-place ops return their argument: its tag grows."""

    def __init__(self) -> None:
        super().__init__()
        self.depth = WeakTensorKeyDictionary()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        out = func(*args, **(kwargs or {}))
        leaves = tree_flatten((args, kwargs or {}))[0]
        tag = max((self.depth.get(x, 0) for x in leaves if isinstance(x, torch.Tensor)), default=0)
        tag += func in CONVOLUTIONS
        for x in tree_flatten(out)[0]:
            if isinstance(x, torch.Tensor):
                self.depth[x] = max(tag, self.depth.get(x, 0))
        return out


def conv_depth(model: Denoiser, side: int = PROBE_SIDE) -> int:
    """Convolution layers on the longest path from any input to any output of `model`'s forward pass, on
    a random batch of the branches it reads (KPCN: its `depth`, 9 at paper size)."""
    device = next((p.device for p in model.parameters()), torch.device("cpu"))
    batch = random_batch(
        side,
        side,
        in_channels=model.in_channels,
        branches=model.branches or BRANCHES,
        generator=torch.Generator().manual_seed(0),
        device=device,
    )
    return path_depth(lambda: model(batch))


def path_depth(run: Callable[[], Any]) -> int:
    """Convolutions on the longest path from the tensors `run` reads to those it returns."""
    mode = _DepthMode()
    with torch.inference_mode(), mode:
        out = run()
    return max(mode.depth.get(x, 0) for x in tree_flatten(out)[0] if isinstance(x, torch.Tensor))
