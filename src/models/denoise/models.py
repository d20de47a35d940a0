"""The learned denoisers: one network per branch of the data (still images: diffuse and specular;
sequences: radiance; `src.models.denoise.base`), or one shared by all branches.

- DPCN (Bako et al. 2017, "direct prediction"): the network outputs the denoised transformed colour.
- KPCN (Bako et al. 2017, Eq. 5-6): the network outputs k*k kernel scores per pixel; `apply_kernel`
  softmax-normalises them and filters the branch's noisy transformed colour.
- Residual KPCN (Vogels et al. 2018 style): the same kernel output from `ResidualKernelNet`, with the
  diffuse and specular branches sharing one network or not (an ablation in the seed thesis).

The branches come from the data (`model.branches: ${dataset.branches}`), so the same YAML and class serve
the still images (two branches, the papers' models) and the sequences (one branch over
`dataset.volume_features`, its output mapped back to linear colour by the sequences' radiance transform).

Input whitening (an ablation) lives inside the model as buffers, so a checkpoint is self-contained and
batches are never whitened outside.
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Mapping
from typing import Literal, TypedDict, Unpack

import torch
from torch import nn

from src.data.kpcn_preprocess import WhiteningStats
from src.errors import ConfigError, DataError
from src.models.denoise.base import Batch, Denoiser, branch_input
from src.models.denoise.kernels import apply_kernel, kernel_application_flops
from src.models.denoise.networks import ConvStack, ResidualKernelNet
from src.models.instantiate import at_least

#: The still images' branches: a model built without `branches` (a benchmark, an old checkpoint) has these.
BRANCHES = ("diffuse", "specular")
OUTPUTS = ("direct", "kernel")
#: Colour channels a direct-prediction network outputs (RGB of the transformed branch colour).
COLOR_CHANNELS = 3
Whitening = Mapping[str, WhiteningStats] | None


class BranchDenoiser(Denoiser):
    """One network per branch, each (whiten ->) network (-> kernel application).

    Args:
        nets: branch name -> its network (registered as `<branch>_net`); pass the SAME module for every
            branch for shared weights (it is then run once on the branches concatenated along N, which is
            faster than one call per branch).
        output: "direct" (net outputs 3 channels: the transformed colour) or "kernel" (net outputs
            kernel_size**2 scores, applied to batch["<branch>_t"]).
        kernel_size: k for output="kernel".
        whiten: hold per-branch mean/std buffers and whiten batch["<branch>_in"] with them.
        in_channels: number of input channels per branch (the length of the whitening statistics).
        whitening: {"<branch>_in": stats} from the training split; with whiten=True and no stats, the
            buffers start at mean 0 / std 1 (a checkpoint load then fills them).
    """

    def __init__(
        self,
        nets: Mapping[str, nn.Module],
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
        self.branches = tuple(nets)
        for branch, net in nets.items():
            setattr(self, f"{branch}_net", net)
        self.output = output
        self.kernel_size = kernel_size if output == "kernel" else None
        self.in_channels = in_channels
        self.whiten = whiten
        if whiten:
            self._register_whitening(whitening or {})

    def net(self, branch: str) -> nn.Module:
        return getattr(self, f"{branch}_net")

    @property
    def shared(self) -> bool:
        """One network for every branch (of more than one)."""
        return len(self.branches) > 1 and len({id(self.net(b)) for b in self.branches}) == 1

    def _register_whitening(self, whitening: Mapping[str, WhiteningStats]) -> None:
        """Buffers `<branch>_mean` / `<branch>_std` of shape (1, C, 1, 1): saved in the state_dict."""
        for branch in self.branches:
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
        return max(self.net(b).halo for b in self.branches) + kernel_radius

    def kernel_flops_per_pixel(self) -> float:
        """FLOPs per pixel outside the convolutions: each branch's kernel application (0 for direct)."""
        return len(self.branches) * kernel_application_flops(self.kernel_size) if self.kernel_size else 0.0

    def check_batch_keys(self, keys: Collection[str]) -> None:
        """Every branch's input group and transformed colour must be in the data (one line otherwise)."""
        missing = [f"{b}{s}" for b in self.branches for s in ("_in", "_t") if f"{b}{s}" not in keys]
        if missing:
            raise DataError(
                f"model reads the {', '.join(self.branches)} branch(es): the data lack {missing}; they have "
                f"{sorted(k for k in keys if k.endswith('_in'))}"
            )

    def _branch_input(self, batch: Batch, branch: str) -> torch.Tensor:
        x = branch_input(batch, branch, self.in_channels)
        if not self.whiten:
            return x
        return (x - getattr(self, f"{branch}_mean")) / getattr(self, f"{branch}_std")

    def network_outputs(self, batch: Batch) -> dict[str, torch.Tensor]:
        """The raw network outputs per branch (colour, or kernel scores before `apply_kernel`)."""
        x = {b: self._branch_input(batch, b) for b in self.branches}
        if self.shared:
            first = x[self.branches[0]]
            all_branches = self.net(self.branches[0])(torch.cat(list(x.values()), dim=0))
            return dict(zip(self.branches, all_branches.split(first.shape[0], dim=0), strict=True))
        return {b: self.net(b)(x[b]) for b in self.branches}

    def forward(self, batch: Batch) -> dict[str, torch.Tensor]:
        raw = self.network_outputs(batch)
        if self.output == "direct":
            return raw
        return {b: apply_kernel(raw[b], batch[f"{b}_t"], self.kernel_size) for b in self.branches}


class _BranchRequired(TypedDict):
    output: Literal["direct", "kernel"]  # direct: the network outputs colour; kernel: k*k kernel scores
    shared: bool  # one network for all branches
    whiten: bool  # per-channel input whitening with the training split's statistics


class BranchArgs(_BranchRequired, total=False):
    """Options of the branch denoisers (`BranchDenoiser`), declared once for their builders.
    (`total=False` rather than `NotRequired`: the latter is not seen under postponed annotations.)"""

    kernel_size: int | None  # k, for output: kernel
    # The data's branches (`${dataset.branches}`); default the still images' two.
    branches: list[str]
    # The training split's {"<branch>_in": stats}, passed by the harness: initialises the whitening
    # buffers (without it they start at mean 0 / std 1, to be filled by a checkpoint load).
    whitening: Whitening


def output_channels(output: str, kernel_size: int | None) -> int:
    """Channels a backbone outputs for `output`: k*k kernel scores (checked: a positive odd k) or the
    3 colour channels of direct prediction."""
    if output == "kernel":
        return at_least("kernel_size", kernel_size if kernel_size is not None else 0, odd=True) ** 2
    return COLOR_CHANNELS


def branch_denoiser(
    make_net: Callable[[int], nn.Module], in_channels: int, opts: BranchArgs
) -> BranchDenoiser:
    """One network (shared) or one per branch, made in branch order, around the common output/whitening
    options (checked by `BranchDenoiser`; the kernel size first, as it sets the networks' output
    channels)."""
    output, kernel_size = opts["output"], opts.get("kernel_size")
    names = list(opts.get("branches") or BRANCHES)
    if len(set(names)) != len(names):
        raise ConfigError(f"model.branches: expected distinct branch names, got {names}")
    out_channels = output_channels(output, kernel_size)
    first = make_net(out_channels)
    nets = {b: first if i == 0 or opts["shared"] else make_net(out_channels) for i, b in enumerate(names)}
    return BranchDenoiser(
        nets,
        output=output,
        in_channels=in_channels,
        kernel_size=kernel_size if output == "kernel" else None,
        whiten=opts["whiten"],
        whitening=opts.get("whitening"),
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
    *, in_channels: int, width: int, depth: int, conv_kernel: int, **opts: Unpack[BranchArgs]
) -> BranchDenoiser:
    """DPCN (`output: direct`) or KPCN (`output: kernel`, Bako et al. 2017): a `ConvStack` per branch."""
    make = conv_stack_maker(in_channels=in_channels, width=width, depth=depth, conv_kernel=conv_kernel)
    return branch_denoiser(make, in_channels, opts)


def residual_denoiser(
    *,
    in_channels: int,
    width: int,
    blocks: int,
    conv_kernel: int,
    predictor_width: int,
    **opts: Unpack[BranchArgs],
) -> BranchDenoiser:
    """Residual KPCN (Vogels et al. 2018 style): a `ResidualKernelNet` per branch, or one shared by both
    (`shared`, an ablation of the seed thesis)."""
    make = residual_maker(
        in_channels=in_channels,
        width=width,
        blocks=blocks,
        conv_kernel=conv_kernel,
        predictor_width=predictor_width,
    )
    return branch_denoiser(make, in_channels, opts)


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
