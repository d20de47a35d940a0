"""The one interface every denoiser (learned or not) implements, so they share training, evaluation,
benchmarks and report tables, on every denoising kind of data (`src/kinds/`).

A batch is a dict of float32 (N, C, H, W) tensors, one frame per row (the trainer flattens the k frames
of its samples into N; a still image is a sequence of one frame). Its colour is split into *branches*,
each with named input groups:

    <branch>_in               the branch's input features, selected by name from the stored candidates
                              (`task.features` for still images, `src.data.features`;
                              `dataset.volume_features` for sequences, `src.data.volume_features`),
                              NOT whitened: a model that whitens holds the statistics as
                              buffers and applies them itself, so a checkpoint is self-contained
    <branch>_t                the branch's noisy colour in its transformed space: what kernels filter
    <branch>_target           the reference in that space (a training target)

The still images have two branches, `diffuse` (d / (albedo + eps)) and `specular` (log(1 + s)); the
sequences one, `radiance` (under `dataset.preprocess.volume_transform`); `src.data.color_spaces` maps a
model's branch outputs back to linear colour for each. Every batch also holds

    color, reference          noisy and reference colour, linear HDR (3)
    albedo, normal            noisy albedo (3), shading normal in [-1, 1] (3)
    depth                     depth normalised to [0, 1] (1)

and, where the data have them: `motion` (sequences: flow in pixels to the next frame), the sequences'
`surface_t` / `volume_t` (the transformed colour's parts), the still images' one-channel guides and GP
features (`src.data.denoise_dataset`).

`Denoiser.forward(batch)` returns a dict:
    branch models:  {<branch>: ...} per branch it reads, in the transformed space (`final_color` makes
                    linear colour of them with the data's colour space);
    colour models:  {"color": ...} linear HDR colour (filters, the U-Net KPCN).
A model declares the branches it reads (`branches`); a kind of data without them refuses it in one line.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from typing import Protocol

import torch
from torch import nn

from src.errors import DataError

Batch = Mapping[str, torch.Tensor]


class ColorSpace(Protocol):
    """How a kind of data makes linear colour of branch outputs (`src.data.color_spaces`)."""

    branches: tuple[str, ...]

    def to_linear(self, outputs: Batch, batch: Batch) -> torch.Tensor: ...


class Denoiser(nn.Module):
    """Base class. `learned` says whether the train stage fits it; `halo` is the number of pixels of
    context one output pixel depends on (receptive-field radius), which tiled inference pads tiles by."""

    learned: bool = True
    #: What the trainer, the summary and tiled inference need to know, declared (not guessed from attribute
    #: names): the network's input channels per branch (None: a filter, which reads the buffers it names),
    #: the multiple its input height and width must have (a U-Net pads to 2^(scales-1)), and the branches
    #: whose input groups it reads (none: a filter).
    in_channels: int | None = None
    size_multiple: int = 1
    branches: tuple[str, ...] = ()

    @property
    def halo(self) -> int:
        raise NotImplementedError

    def forward(self, batch: Batch) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def kernel_flops_per_pixel(self) -> float:
        """FLOPs per output pixel outside the convolutions (kernel application, composition across scales),
        which the summary adds to the convolution FLOPs it measures: 0 for a network that outputs colour."""
        return 0.0

    def compositor_modules(self) -> nn.Module | None:
        """The modules whose convolutions combine scales (shown apart in the summary); None: none."""
        return None

    def flops_per_pixel(self) -> float | None:
        """A filter's whole cost per pixel (a learned model's is measured instead); None: unknown."""
        return None

    def check_batch_keys(self, keys: Collection[str]) -> None:
        """Raise a one-line error naming what `forward` would miss in batches with tensor `keys` (read from
        the data's index before any image is denoised). Default: nothing beyond the common keys."""


def final_color(outputs: Mapping[str, torch.Tensor], batch: Batch, space: ColorSpace) -> torch.Tensor:
    """Linear HDR colour from a denoiser's outputs: its "color", or its branch outputs mapped back by the
    data's colour space (still images: c = (albedo + eps) * d' + exp(s') - 1)."""
    if "color" in outputs:
        return outputs["color"]
    return space.to_linear(outputs, batch)


def branch_input(batch: Batch, branch: str, in_channels: int) -> torch.Tensor:
    """batch["<branch>_in"], checked against the model's input channels (one-line DataError otherwise)."""
    key = f"{branch}_in"
    if key not in batch:
        raise DataError(
            f"batch has no {key!r}: this model reads the {branch} branch; got keys {sorted(batch)}"
        )
    x = batch[key]
    if x.ndim != 4 or x.shape[1] != in_channels:
        raise DataError(f"batch[{key!r}] is {tuple(x.shape)}, expected (N, {in_channels}, H, W)")
    return x
