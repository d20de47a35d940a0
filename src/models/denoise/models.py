"""The learned denoisers: one network per branch (diffuse, specular), or one shared by both.

- DPCN (Bako et al. 2017, "direct prediction"): the network outputs the denoised transformed colour.
- KPCN (Bako et al. 2017, Eq. 5-6): the network outputs k*k kernel scores per pixel; `apply_kernel`
  softmax-normalises them and filters the branch's noisy transformed colour.
- Residual KPCN (Vogels et al. 2018 style): the same kernel output from `ResidualKernelNet`, with the
  diffuse and specular branches sharing one network or not (an ablation in the seed thesis).

Input whitening (an ablation) lives inside the model as buffers, so a checkpoint is self-contained and
batches are never whitened outside.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Literal, TypedDict, Unpack

import torch
from torch import nn

from src.data.kpcn_preprocess import WhiteningStats
from src.errors import ConfigError, DataError
from src.models.denoise.base import Batch, Denoiser
from src.models.denoise.kernels import apply_kernel, kernel_application_flops
from src.models.denoise.networks import ConvStack, ResidualKernelNet
from src.models.instantiate import at_least

BRANCHES = ("diffuse", "specular")
OUTPUTS = ("direct", "kernel")
#: Colour channels a direct-prediction network outputs (RGB of the transformed branch colour).
COLOR_CHANNELS = 3
Whitening = Mapping[str, WhiteningStats] | None


class TwoBranchDenoiser(Denoiser):
    """Diffuse and specular branches, each (whiten ->) network (-> kernel application).

    Args:
        diffuse_net, specular_net: the branch networks; pass the SAME module for shared weights (it is then
            run once on both branches concatenated along N, which is faster than two calls).
        output: "direct" (net outputs 3 channels: the transformed colour) or "kernel" (net outputs
            kernel_size**2 scores, applied to batch["<branch>_t"]).
        kernel_size: k for output="kernel".
        whiten: hold per-branch mean/std buffers and whiten batch["<branch>_in"] with them.
        in_channels: number of input channels (the length of the whitening statistics).
        whitening: {"diffuse_in": stats, "specular_in": stats} from the training split; with whiten=True and
            no stats, the buffers start at mean 0 / std 1 (a checkpoint load then fills them).
    """

    learned = True

    def __init__(
        self,
        diffuse_net: nn.Module,
        specular_net: nn.Module,
        *,
        output: str,
        in_channels: int,
        kernel_size: int | None = None,
        whiten: bool = False,
        whitening: Mapping[str, WhiteningStats] | None = None,
    ) -> None:
        super().__init__()
        if output not in OUTPUTS:
            raise ConfigError(f"model.output: unknown {output!r}; expected one of {list(OUTPUTS)}")
        if output == "kernel" and (kernel_size is None or kernel_size < 1 or kernel_size % 2 == 0):
            raise ConfigError(f"model.kernel_size: expected a positive odd integer, got {kernel_size!r}")
        self.diffuse_net = diffuse_net
        self.specular_net = specular_net
        self.output = output
        self.kernel_size = kernel_size if output == "kernel" else None
        self.in_channels = in_channels
        self.whiten = whiten
        if whiten:
            self._register_whitening(whitening or {})

    @property
    def shared(self) -> bool:
        return self.diffuse_net is self.specular_net

    def _register_whitening(self, whitening: Mapping[str, WhiteningStats]) -> None:
        """Buffers `<branch>_mean` / `<branch>_std` of shape (1, C, 1, 1): saved in the state_dict."""
        for branch in BRANCHES:
            key = f"{branch}_in"
            stats = whitening.get(key)
            mean = torch.zeros(self.in_channels) if stats is None else torch.as_tensor(stats.mean)
            std = torch.ones(self.in_channels) if stats is None else torch.as_tensor(stats.std)
            if mean.numel() != self.in_channels or std.numel() != self.in_channels:
                raise ConfigError(
                    f"whitening[{key!r}]: {mean.numel()} means / {std.numel()} stds, "
                    f"model.in_channels is {self.in_channels}"
                )
            self.register_buffer(f"{branch}_mean", mean.float().view(1, -1, 1, 1))
            self.register_buffer(f"{branch}_std", std.float().view(1, -1, 1, 1))

    @property
    def halo(self) -> int:
        """Network receptive field plus the kernel radius (kernels read k//2 pixels around each pixel)."""
        kernel_radius = self.kernel_size // 2 if self.kernel_size else 0
        return max(self.diffuse_net.halo, self.specular_net.halo) + kernel_radius

    def kernel_flops_per_pixel(self) -> float:
        """FLOPs per pixel outside the convolutions: each branch's kernel application (0 for direct)."""
        return len(BRANCHES) * kernel_application_flops(self.kernel_size) if self.kernel_size else 0.0

    def _branch_input(self, batch: Batch, branch: str) -> torch.Tensor:
        x = batch[f"{branch}_in"]
        if x.ndim != 4 or x.shape[1] != self.in_channels:
            raise DataError(
                f"batch['{branch}_in'] is {tuple(x.shape)}, expected (N, {self.in_channels}, H, W)"
            )
        if not self.whiten:
            return x
        return (x - getattr(self, f"{branch}_mean")) / getattr(self, f"{branch}_std")

    def network_outputs(self, batch: Batch) -> dict[str, torch.Tensor]:
        """The raw network outputs per branch (colour, or kernel scores before `apply_kernel`)."""
        x = {b: self._branch_input(batch, b) for b in BRANCHES}
        if self.shared:
            both = self.diffuse_net(torch.cat([x["diffuse"], x["specular"]], dim=0))
            return dict(zip(BRANCHES, both.split(x["diffuse"].shape[0], dim=0), strict=True))
        return {"diffuse": self.diffuse_net(x["diffuse"]), "specular": self.specular_net(x["specular"])}

    def forward(self, batch: Batch) -> dict[str, torch.Tensor]:
        raw = self.network_outputs(batch)
        if self.output == "direct":
            return raw
        return {b: apply_kernel(raw[b], batch[f"{b}_t"], self.kernel_size) for b in BRANCHES}


class _TwoBranchRequired(TypedDict):
    output: Literal["direct", "kernel"]  # direct: the network outputs colour; kernel: k*k kernel scores
    shared: bool  # one network for both branches
    whiten: bool  # per-channel input whitening with the training split's statistics


class TwoBranchArgs(_TwoBranchRequired, total=False):
    """Options of both two-branch denoisers (`TwoBranchDenoiser`), declared once for their builders.
    (`total=False` rather than `NotRequired`: the latter is not seen under postponed annotations.)"""

    kernel_size: int | None  # k, for output: kernel
    # The training split's {"diffuse_in": stats, "specular_in": stats}, passed by the harness: initialises the
    # whitening buffers (without it they start at mean 0 / std 1, to be filled by a checkpoint load).
    whitening: Whitening


def output_channels(output: str, kernel_size: int | None) -> int:
    """Channels a backbone outputs for `output`: k*k kernel scores (checked: a positive odd k) or the
    3 colour channels of direct prediction."""
    if output == "kernel":
        return at_least("kernel_size", kernel_size if kernel_size is not None else 0, odd=True) ** 2
    return COLOR_CHANNELS


def _two_branch(
    make_net: Callable[[int], nn.Module], in_channels: int, branches: TwoBranchArgs
) -> TwoBranchDenoiser:
    """One network (shared) or two, around the common output/whitening options (checked by
    `TwoBranchDenoiser`; the kernel size first, as it sets the networks' output channels)."""
    output, kernel_size = branches["output"], branches.get("kernel_size")
    out_channels = output_channels(output, kernel_size)
    diffuse = make_net(out_channels)
    specular = diffuse if branches["shared"] else make_net(out_channels)
    return TwoBranchDenoiser(
        diffuse,
        specular,
        output=output,
        in_channels=in_channels,
        kernel_size=kernel_size if output == "kernel" else None,
        whiten=branches["whiten"],
        whitening=branches.get("whitening"),
    )


def conv_stack_maker(
    *, in_channels: int, width: int, depth: int, conv_kernel: int
) -> Callable[[int], ConvStack]:
    """out_channels -> a `ConvStack` of these (range-checked) sizes: the DPCN/KPCN backbone."""
    sizes = {
        "in_channels": at_least("in_channels", in_channels),
        "width": at_least("width", width),
        "depth": at_least("depth", depth),
        "conv_kernel": at_least("conv_kernel", conv_kernel, odd=True),
    }
    return lambda out_channels: ConvStack(**sizes, out_channels=out_channels)


def residual_maker(
    *, in_channels: int, width: int, blocks: int, conv_kernel: int, predictor_width: int
) -> Callable[[int], ResidualKernelNet]:
    """out_channels -> a `ResidualKernelNet` of these (range-checked) sizes: the residual KPCN backbone."""
    sizes = {
        "in_channels": at_least("in_channels", in_channels),
        "width": at_least("width", width),
        "blocks": at_least("blocks", blocks, minimum=0),
        "conv_kernel": at_least("conv_kernel", conv_kernel, odd=True),
        "predictor_width": at_least("predictor_width", predictor_width),
    }
    return lambda out_channels: ResidualKernelNet(**sizes, out_channels=out_channels)


def conv_stack_denoiser(
    *, in_channels: int, width: int, depth: int, conv_kernel: int, **branches: Unpack[TwoBranchArgs]
) -> TwoBranchDenoiser:
    """DPCN (`output: direct`) or KPCN (`output: kernel`, Bako et al. 2017): a `ConvStack` per branch."""
    make = conv_stack_maker(in_channels=in_channels, width=width, depth=depth, conv_kernel=conv_kernel)
    return _two_branch(make, in_channels, branches)


def residual_denoiser(
    *,
    in_channels: int,
    width: int,
    blocks: int,
    conv_kernel: int,
    predictor_width: int,
    **branches: Unpack[TwoBranchArgs],
) -> TwoBranchDenoiser:
    """Residual KPCN (Vogels et al. 2018 style): a `ResidualKernelNet` per branch, or one shared by both
    (`shared`, an ablation of the seed thesis)."""
    make = residual_maker(
        in_channels=in_channels,
        width=width,
        blocks=blocks,
        conv_kernel=conv_kernel,
        predictor_width=predictor_width,
    )
    return _two_branch(make, in_channels, branches)


def _tile_starts(size: int, tile: int) -> range:
    return range(0, size, tile)


def infer_tiled(model: Denoiser, batch: Batch, tile: int) -> dict[str, torch.Tensor]:
    """Run `model` on tile x tile pieces of a full frame, each padded by `model.halo` pixels of real
    context, and stitch the outputs. With a halo at least the receptive-field radius, the result equals
    one full-frame forward (zero padding only ever occurs at the true image border), while peak memory
    is bounded by the tile size. `tile <= 0`, a frame no larger than one tile, or `halo is None` (a model
    that must see the whole frame, e.g. OIDN) run the frame in one call.
    """
    height, width = next(iter(batch.values())).shape[-2:]
    halo = model.halo
    if tile <= 0 or halo is None or (height <= tile and width <= tile):
        return model(batch)
    out: dict[str, torch.Tensor] = {}
    for y0 in _tile_starts(height, tile):
        for x0 in _tile_starts(width, tile):
            y1, x1 = min(y0 + tile, height), min(x0 + tile, width)
            ya, xa = max(y0 - halo, 0), max(x0 - halo, 0)
            yb, xb = min(y1 + halo, height), min(x1 + halo, width)
            piece = model({k: v[..., ya:yb, xa:xb] for k, v in batch.items()})
            for key, value in piece.items():
                if key not in out:
                    out[key] = value.new_empty((*value.shape[:-2], height, width))
                out[key][..., y0:y1, x0:x1] = value[..., y0 - ya : y1 - ya, x0 - xa : x1 - xa]
    return out
