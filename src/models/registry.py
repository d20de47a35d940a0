"""Build any denoiser from its `model:` config group (conf/model/*.yaml), learned or not.

`model.architecture` selects the builder:
    conv_stack       DPCN / KPCN (Bako et al. 2017): `ConvStack` per branch
    residual         residual KPCN (Vogels et al. 2018 style): `ResidualKernelNet` per branch or shared
    cross_bilateral  `src.models.filters.cross_bilateral.CrossBilateralFilter`
    oidn             `src.models.filters.oidn.OIDNDenoiser`
A missing or invalid key is a one-line `ConfigError` naming `model.<key>`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from torch import nn

from src.data.kpcn_preprocess import WhiteningStats
from src.errors import ConfigError
from src.models import config_readers as read
from src.models.denoise.base import Denoiser
from src.models.denoise.models import OUTPUTS, TwoBranchDenoiser
from src.models.denoise.networks import ConvStack, ResidualKernelNet

#: Colour channels a direct-prediction network outputs (RGB of the transformed branch colour).
COLOR_CHANNELS = 3

Whitening = Mapping[str, WhiteningStats] | None


def _output(cfg: Mapping[str, Any]) -> tuple[str, int | None, int]:
    """(output, kernel_size, network output channels) from model.output / model.kernel_size."""
    output = read.value(cfg, "output")
    if output not in OUTPUTS:
        raise ConfigError(f"model.output: unknown {output!r}; expected one of {list(OUTPUTS)}")
    if output == "direct":
        return output, None, COLOR_CHANNELS
    k = read.integer(cfg, "kernel_size", odd=True)
    return output, k, k * k


def _two_branch(cfg: Mapping[str, Any], make_net: Callable[[int], nn.Module], whitening: Whitening):
    """One network (shared) or two, around the common output/whitening options."""
    output, kernel_size, out_channels = _output(cfg)
    diffuse = make_net(out_channels)
    specular = diffuse if read.boolean(cfg, "shared") else make_net(out_channels)
    return TwoBranchDenoiser(
        diffuse,
        specular,
        output=output,
        in_channels=read.integer(cfg, "in_channels"),
        kernel_size=kernel_size,
        whiten=read.boolean(cfg, "whiten"),
        whitening=whitening,
    )


def _conv_stack(cfg: Mapping[str, Any], whitening: Whitening) -> Denoiser:
    def make(out_channels: int) -> nn.Module:
        return ConvStack(
            in_channels=read.integer(cfg, "in_channels"),
            width=read.integer(cfg, "width"),
            depth=read.integer(cfg, "depth"),
            conv_kernel=read.integer(cfg, "conv_kernel", odd=True),
            out_channels=out_channels,
        )

    return _two_branch(cfg, make, whitening)


def _residual(cfg: Mapping[str, Any], whitening: Whitening) -> Denoiser:
    def make(out_channels: int) -> nn.Module:
        return ResidualKernelNet(
            in_channels=read.integer(cfg, "in_channels"),
            width=read.integer(cfg, "width"),
            blocks=read.integer(cfg, "blocks", minimum=0),
            conv_kernel=read.integer(cfg, "conv_kernel", odd=True),
            predictor_width=read.integer(cfg, "predictor_width"),
            out_channels=out_channels,
        )

    return _two_branch(cfg, make, whitening)


def _cross_bilateral(cfg: Mapping[str, Any], whitening: Whitening) -> Denoiser:
    # Imported lazily: the filters are optional baselines, written and tested on their own.
    from src.models.filters.cross_bilateral import CrossBilateralFilter

    return CrossBilateralFilter.from_config(cfg)


def _oidn(cfg: Mapping[str, Any], whitening: Whitening) -> Denoiser:
    from src.models.filters.oidn import OIDNDenoiser

    return OIDNDenoiser.from_config(cfg)


BUILDERS: dict[str, Callable[[Mapping[str, Any], Whitening], Denoiser]] = {
    "conv_stack": _conv_stack,
    "residual": _residual,
    "cross_bilateral": _cross_bilateral,
    "oidn": _oidn,
}


def build_denoiser(model_cfg: Mapping[str, Any], whitening: Whitening = None) -> Denoiser:
    """The denoiser `model_cfg["architecture"]` names, built from the config (DictConfig or dict).

    `whitening` ({"diffuse_in": stats, "specular_in": stats}, training split) initialises the whitening
    buffers of learned models with `whiten: true`; without it they start at mean 0 / std 1 (to be filled
    by a checkpoint load). Non-learned filters ignore it.
    """
    cfg = read.as_dict(model_cfg)
    architecture = read.value(cfg, "architecture")
    if architecture not in BUILDERS:
        raise ConfigError(f"model.architecture: unknown {architecture!r}; expected one of {list(BUILDERS)}")
    try:
        return BUILDERS[architecture](cfg, whitening)
    except ValueError as err:  # a size the network constructors reject (e.g. an even conv kernel)
        raise ConfigError(f"model ({architecture}): {' '.join(str(err).split())}") from err
