"""KPCN, DPCN and residual KPCN on the volumetric *frame batch* (`base.py`): one branch, not two.

The volumetric sequences have no diffuse/specular split: a frame batch holds `inputs` (the
`task.volume_features` channels) and the noisy colour `color_t` under `task.preprocess.volume_transform`.
These are the Bako et al. 2017 / seed-thesis models with one network over `inputs`:

- `output: kernel` (KPCN, residual KPCN): the network predicts k*k scores per pixel; `apply_kernel`
  filters the *transformed* noisy colour `color_t` with them (as Bako et al. filter their transformed
  branches), and the result is mapped back with `inverse_volume_transform`;
- `output: direct` (DPCN): the network outputs the transformed colour, mapped back the same way.

Every model of a frame batch returns {"color": linear HDR colour}.

The factories take the same YAML keys as `conv_stack_denoiser` / `residual_denoiser`, plus `transform`,
so `conf/model/{dpcn,kpcn,resnet}.yaml` serve both datasets (`conf/model_dataset/<model>_volumetric.yaml`
only swaps `_target_`, `in_channels` and adds `transform`):

- `shared` is accepted and ignored: with one branch there is nothing to share;
- `whiten: true` is a ConfigError: input whitening statistics exist only for the still-image shards
  (`diffuse_in`/`specular_in`), not for the volumetric frames.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, Unpack

import torch
from torch import nn

from src.data.volume_shards import VOLUME_TRANSFORMS, inverse_volume_transform
from src.errors import ConfigError, DataError
from src.models.denoise.base import Batch, Denoiser
from src.models.denoise.kernels import apply_kernel, kernel_application_flops
from src.models.denoise.models import (
    OUTPUTS,
    TwoBranchArgs,
    conv_stack_maker,
    output_channels,
    residual_maker,
)

Transform = Literal["log_modulus", "none"]


def check_transform(transform: str) -> str:
    """`transform` if it is a `task.preprocess.volume_transform` choice, else a one-line ConfigError."""
    if transform not in VOLUME_TRANSFORMS:
        raise ConfigError(f"model.transform: expected one of {list(VOLUME_TRANSFORMS)}, got {transform!r}")
    return transform


def frame_batch_builder(builder: Callable) -> Callable:
    """Mark a builder whose models read frame batches (`dataset=volumetric`), so that a job can refuse
    to train or evaluate them on the still-image datasets before anything runs."""
    builder.frame_batch = True
    return builder


def check_frame_input(batch: Batch, in_channels: int) -> torch.Tensor:
    """batch["inputs"], checked against the model's input channels (one-line DataError otherwise)."""
    if "inputs" not in batch:
        raise DataError(
            "batch has no 'inputs': this model reads the volumetric frame batches (dataset=volumetric), "
            f"got keys {sorted(batch)}"
        )
    x = batch["inputs"]
    if x.ndim != 4 or x.shape[1] != in_channels:
        raise DataError(f"batch['inputs'] is {tuple(x.shape)}, expected (N, {in_channels}, H, W)")
    return x


class FrameKernelDenoiser(Denoiser):
    """One network over batch["inputs"]; kernel output filters batch["color_t"], direct output is the
    transformed colour; either way the result is inverse-transformed to linear {"color"}."""

    learned = True
    frame_batch = True

    def __init__(
        self, net: nn.Module, *, output: str, in_channels: int, transform: str, kernel_size: int | None
    ) -> None:
        super().__init__()
        if output not in OUTPUTS:
            raise ConfigError(f"model.output: unknown {output!r}; expected one of {list(OUTPUTS)}")
        self.net = net
        self.output = output
        self.in_channels = in_channels
        self.transform = check_transform(transform)
        self.kernel_size = kernel_size if output == "kernel" else None

    @property
    def halo(self) -> int:
        """The network's receptive field plus the kernel radius."""
        return self.net.halo + (self.kernel_size // 2 if self.kernel_size else 0)

    def kernel_flops_per_pixel(self) -> float:
        """FLOPs per pixel outside the convolutions: one branch's kernel application (0 for direct)."""
        return kernel_application_flops(self.kernel_size) if self.kernel_size else 0

    def forward(self, batch: Batch) -> dict[str, torch.Tensor]:
        raw = self.net(check_frame_input(batch, self.in_channels))
        transformed = (
            raw if self.output == "direct" else apply_kernel(raw, batch["color_t"], self.kernel_size)
        )
        return {"color": inverse_volume_transform(transformed, self.transform)}


def _one_branch(
    make_net: Callable[[int], nn.Module], in_channels: int, transform: str, branches: TwoBranchArgs
) -> FrameKernelDenoiser:
    """The frame model around one backbone; `shared` is ignored (one branch), `whiten` must be false."""
    if branches["whiten"]:
        raise ConfigError(
            "model.whiten: true is not supported on dataset=volumetric (no whitening statistics of the "
            "frame inputs); set model.whiten=false"
        )
    output, kernel_size = branches["output"], branches.get("kernel_size")
    check_transform(transform)
    net = make_net(output_channels(output, kernel_size))
    return FrameKernelDenoiser(
        net, output=output, in_channels=in_channels, transform=transform, kernel_size=kernel_size
    )


@frame_batch_builder
def frame_conv_stack_denoiser(
    *,
    in_channels: int,
    width: int,
    depth: int,
    conv_kernel: int,
    transform: Transform,
    **branches: Unpack[TwoBranchArgs],
) -> FrameKernelDenoiser:
    """DPCN (`output: direct`) or KPCN (`output: kernel`) on frame batches: one `ConvStack`."""
    make = conv_stack_maker(in_channels=in_channels, width=width, depth=depth, conv_kernel=conv_kernel)
    return _one_branch(make, in_channels, transform, branches)


@frame_batch_builder
def frame_residual_denoiser(
    *,
    in_channels: int,
    width: int,
    blocks: int,
    conv_kernel: int,
    predictor_width: int,
    transform: Transform,
    **branches: Unpack[TwoBranchArgs],
) -> FrameKernelDenoiser:
    """Residual KPCN (Vogels et al. 2018 style) on frame batches: one `ResidualKernelNet`."""
    make = residual_maker(
        in_channels=in_channels,
        width=width,
        blocks=blocks,
        conv_kernel=conv_kernel,
        predictor_width=predictor_width,
    )
    return _one_branch(make, in_channels, transform, branches)
