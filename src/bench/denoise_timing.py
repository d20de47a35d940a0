"""What `denoise` times: each denoiser prepared as a table row and a function that denoises one frame
(a learned model, a kernel model's networks alone, OIDN); `src.bench.denoise` times them all in rounds."""

from __future__ import annotations

from collections.abc import Callable, Mapping, MutableMapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import nn

from src.bench.conv_depth import conv_depth
from src.bench.model_configs import load_model_config
from src.bench.timing import Rounds, Spread
from src.errors import one_line
from src.models.denoise.base import Denoiser
from src.models.denoise.models import BRANCHES, BranchDenoiser, infer_tiled
from src.models.denoise.summary import flops_per_pixel, random_batch
from src.models.instantiate import build_method
from src.models.parameters import count_parameters

#: Bench names that are no `conf/model` name: (the conf/model name, the conf/dataset it is composed
#: with). `kpcn_frame` is the KPCN that the `unet_vs_kpcn` study trains per frame on the sequences
#: (dataset=volumetric: one `radiance` branch with the sequences' `dataset.volume_features` inputs), where
#: `kpcn` is Bako et al. 2017's two-branch (diffuse + specular) KPCN of the still images.
VARIANTS = {"kpcn_frame": ("kpcn", "volumetric")}

Batches = MutableMapping[tuple[tuple[str, ...], int], dict[str, torch.Tensor]]


@dataclass
class Row:
    """One line of the result table, and its timed function's name in the rounds (`key`)."""

    name: str
    seconds: float | None  # median seconds per frame over the rounds
    flops_per_pixel: float | None = None
    params: int | None = None
    note: str = ""
    key: str = ""  # the name in the rounds, metrics and rounds.csv (a metric-safe name; "": `name`)
    spread: Spread | None = None  # of the seconds per frame over the rounds
    depth: int | None = None  # conv layers on the longest input-to-output path (`conv_depth`)
    width: str = ""  # the hidden conv layers' channels (the config's `width` or `widths`)

    def __post_init__(self) -> None:
        self.key = self.key or self.name


#: A prepared row and the function that denoises one frame (None: it cannot run here; the note says why).
Prepared = tuple[Row, Callable[[], Any] | None]


class NetworkOnly(nn.Module):
    """A kernel model's networks without `apply_kernel` (same tiles, same halo): the "conv stack alone"
    that the kernel-application overhead is measured against."""

    learned = True

    def __init__(self, model: BranchDenoiser) -> None:
        super().__init__()
        self.model = model

    @property
    def halo(self) -> int:
        return self.model.halo

    def forward(self, batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return self.model.network_outputs(batch)


def frame_tiles(size: int, tile: int) -> list[slice]:
    step = size if tile <= 0 else tile
    return [slice(start, min(start + step, size)) for start in range(0, size, step)]


def bench_config(name: str, profile: str) -> dict[str, Any]:
    """The model config of bench name `name` (a conf/model name, or one of `VARIANTS`)."""
    model, dataset = VARIANTS.get(name, (name, None))
    return load_model_config(model, profile, dataset=dataset)


def model_batch(model: Denoiser, batches: Batches, height: int, width: int, seed: int, device):
    """A random frame of the branches `model` reads with its `in_channels` (the still images' two
    branches, or the sequences' radiance: `dataset.volume_features` of the profile), made once per
    (branches, in_channels) and shared by the models that read the same."""
    branches = tuple(model.branches or BRANCHES)
    key = (branches, int(model.in_channels))
    if key not in batches:
        generator = torch.Generator().manual_seed(seed)
        batches[key] = random_batch(
            height, width, in_channels=key[1], branches=branches, generator=generator, device=device
        )
    return batches[key]


def _width(cfg: Mapping[str, Any]) -> str:
    widths = cfg.get("widths", cfg.get("width"))
    if isinstance(widths, list | tuple):
        return "-".join(str(w) for w in sorted(set(widths)))
    return "" if widths is None else str(widths)


def bench_model(
    name: str, profile: str, batches: Batches, size, tile: int, device, seed: int
) -> list[Prepared]:
    """Rows for one model: itself, and for kernel models its networks alone (`NetworkOnly`), each with
    the function that denoises the frame in tiles. The model reads a random frame of its own branches
    and `in_channels` (`model_batch`); `size` is the frame's (height, width)."""
    cfg = bench_config(name, profile)
    torch.manual_seed(seed)
    model: Denoiser = build_method(cfg).to(device).eval()
    batch = model_batch(model, batches, *size, seed, device)
    flops = flops_per_pixel(model)
    params = count_parameters(model)
    branches = tuple(model.branches or BRANCHES)
    note = cfg["_target_"].rsplit(".", 1)[-1] + (f", output {cfg['output']}" if "output" in cfg else "")
    note += f", {'+'.join(branches)} x {model.in_channels} inputs"
    depth = conv_depth(model)
    row = Row(name, None, flops["total"], params, note, depth=depth, width=_width(cfg))
    prepared: list[Prepared] = [(row, lambda: infer_tiled(model, batch, tile))]
    if isinstance(model, BranchDenoiser) and model.output == "kernel":
        net = NetworkOnly(model)
        net_row = Row(
            f"{name} (net only)", None, flops["conv"], params, "no apply_kernel", key=f"{name}_net_only"
        )
        prepared.append((net_row, lambda: infer_tiled(net, batch, tile)))
    return prepared


def _oidn_call(model, batch: Mapping[str, torch.Tensor]) -> Callable[[], torch.Tensor]:
    """OIDN's forward on the batch's device: the model's options and input clamps (`OIDNDenoiser`), with
    torch tensors handed to pyoidn, which runs CUDA tensors on OIDN's CUDA device and CPU tensors on its
    CPU device. (The model's own forward goes through NumPy, i.e. always OIDN's CPU device: what the
    evaluation's numbers are, but no speed reference for a model on a GPU.)"""
    import pyoidn

    def hwc(x: torch.Tensor, lo: float | None, hi: float | None) -> torch.Tensor:
        return x[0].float().clamp(min=lo, max=hi).permute(1, 2, 0).contiguous()

    def run() -> torch.Tensor:
        color = hwc(batch["color"], 0.0, None if model.hdr else 1.0)
        albedo = hwc(batch["albedo"], 0.0, 1.0) if model.use_albedo else None
        normal = hwc(batch["normal"], -1.0, 1.0) if model.use_normal else None
        out = pyoidn.denoise(
            color, albedo, normal, hdr=model.hdr, quality=model.quality, clean_aux=model.clean_aux
        )
        return out.permute(2, 0, 1).unsqueeze(0)

    return run


def bench_oidn(profile: str, batch, device: torch.device) -> Prepared:
    """OIDN on the full frame (it is never tiled) on the bench's device, run once here to see that it
    works (an extra untimed call), or a row saying why it cannot run here."""
    try:
        run = _oidn_call(build_method(load_model_config("oidn", profile)), batch)
        run()
    except Exception as err:  # import failure, missing native library, unsupported device...
        return Row("oidn", None, note=f"unavailable ({one_line(err)})"), None
    return Row("oidn", None, note=f"pyoidn on {device.type}, full frame"), run


def timed_rows(prepared: list[Prepared], rounds: Rounds) -> list[Row]:
    """The rows with their times: each timed row's seconds per frame over the rounds (its spread) and
    their median; a row that could not run keeps `seconds` None."""
    rows = []
    for row, run in prepared:
        if run is not None:
            row.spread = Spread.of(rounds.seconds[row.key])
            row.seconds = row.spread.median
        rows.append(row)
    return rows
