"""The one interface every denoiser (learned or not) implements, so they share training, evaluation,
benchmarks and report tables.

A batch is a dict of float32 (N, C, H, W) tensors, as `src.data.denoise_dataset` yields them:

    diffuse_in, specular_in   the `task.features` channels (`src.data.features`; the paper's 28 by
                              default), in the order configured, NOT whitened: a model
                              that whitens holds the statistics as buffers and applies them itself, so a
                              checkpoint is self-contained
    diffuse_t, specular_t     transformed noisy colours (d / (albedo + eps), log(1 + s)): what kernels filter
    albedo, normal            noisy albedo (3), world-space shading normal in [-1, 1] (3)
    depth                     depth normalised to [0, 1] by the image maximum (1)
    color, reference          noisy and reference colour, linear HDR (3)
    diffuse_target, specular_target   transformed reference (training targets)

A *frame batch* of the volumetric sequences (`dataset=volumetric`, `src.data.sequence_dataset`: one frame
per row, the frames of a training sample or sequence flattened into N) holds instead:

    inputs                    the `task.volume_features` channels (`src.data.volume_features`), radiance
                              and unbounded buffers under `task.preprocess.volume_transform`, NOT whitened
    color_t, surface_t, volume_t   the noisy colour and its surface / volume parts (3 each), transformed
    color, reference          noisy and reference colour, linear HDR (3)
    target, target_surface, target_volume   the reference colour / surface / volume, transformed
    albedo, normal, depth     guides as stored (albedo, normal in [-1, 1], depth over the sequence's scale)
    motion                    screen-space flow to the next frame, pixels (2)

and every model of it returns {"color": ...}, linear HDR colour (a network in the transformed space maps
its output back itself), so learned models and filters share the sequence trainer and evaluation.

`Denoiser.forward(batch)` returns a dict:
    learned models: {"diffuse": ..., "specular": ...} in the transformed space (then `final_color`
                    rebuilds linear colour with the inverse transform);
    filters:        {"color": ...} linear HDR colour.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping

import torch
from torch import nn

from src.data.kpcn_preprocess import rebuild_color

Batch = Mapping[str, torch.Tensor]


class Denoiser(nn.Module):
    """Base class. `learned` says whether the train stage fits it; `halo` is the number of pixels of
    context one output pixel depends on (receptive-field radius), which tiled inference pads tiles by."""

    learned: bool = True
    #: What the trainer, the summary and tiled inference need to know, declared (not guessed from attribute
    #: names): the network's input channels (None: a filter, which reads the buffers it names), the
    #: multiple its input height and width must have (a U-Net pads to 2^(scales-1)), and whether it reads
    #: volumetric frame batches rather than diffuse/specular ones.
    in_channels: int | None = None
    size_multiple: int = 1
    frame_batch: bool = False

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


def final_color(outputs: Mapping[str, torch.Tensor], batch: Batch, eps: float) -> torch.Tensor:
    """Linear HDR colour from a denoiser's outputs: its "color", or the inverse transform of its
    diffuse/specular (c = (albedo + eps) * d' + exp(s') - 1)."""
    if "color" in outputs:
        return outputs["color"]
    return rebuild_color(outputs["diffuse"], outputs["specular"], batch["albedo"], eps)
