"""Benchmarks: ``python -m src.bench denoise [--width 1280 --height 720 --repeats 3 --device auto
--models dpcn,kpcn,resnet --profile paper]``.

`denoise` times full-frame inference of the learned denoisers (random weights, seeded; random inputs:
speed does not depend on the values) and prints, in one run:
- each model's seconds per frame and per megapixel, FLOPs and achieved GFLOP/s;
- KPCN/DPCN time and FLOP ratios (the FLOP ratio ~1.6 comes from KPCN's 441-channel output layer);
- the kernel-application overhead: a kernel model's total time / the same network without
  `apply_kernel` ("at equal backbone, KPCN costs <= ~1.2x": the Bako et al. 2017 claim that applying the
  kernel is cheap; a per-pixel Python loop in the seed thesis took 140 s per frame);
- OIDN on the same frame, if `pyoidn` works here;
- a plain `F.conv2d` (100 -> 100 channels, 5x5, the DPCN hidden layer) on the same frame, as the
  achievable conv throughput of this device.

Frames are processed in tiles (plus each model's halo, so results equal a full-frame pass) to bound
memory; on CUDA the default is the whole frame at once. GFLOP/s counts the useful FLOPs of one frame
(`flops_per_pixel` x pixels): work redone in tile halos shows up as lower throughput, not more FLOPs.
Times are medians, with a model and its network-only variant timed alternately so that load on a
shared machine does not bias their ratio.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable, Mapping, Sequence
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from hydra import compose, initialize_config_dir
from hydra.errors import HydraException
from omegaconf import OmegaConf
from torch import nn

from src.errors import NrbenchError
from src.models.denoise.base import Denoiser
from src.models.denoise.models import TwoBranchDenoiser, infer_tiled
from src.models.denoise.summary import count_parameters, flops_per_pixel, random_batch
from src.models.registry import build_denoiser

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
#: Tile side on CPU (pixels, before the halo): bounds activation memory at paper width.
CPU_TILE = 256
#: The reference convolution: the DPCN/KPCN hidden layer of Bako et al. 2017 (100 -> 100 channels, 5x5).
BASELINE_CONV = {"channels": 100, "kernel": 5}
AUTOCAST_DTYPES = {"none": None, "bf16": torch.bfloat16, "fp16": torch.float16}


@dataclass
class Row:
    """One line of the result table."""

    name: str
    seconds: float | None  # median seconds per frame
    flops_per_pixel: float | None = None
    params: int | None = None
    note: str = ""


def load_model_config(name: str, profile: str) -> dict[str, Any]:
    """The `model:` group as `python -m src.run model=<name> profile=<profile>` composes it."""
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=[f"model={name}", f"profile={profile}"])
    return OmegaConf.to_container(cfg.model, resolve=True)  # type: ignore[return-value]


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_calls(
    fns: Sequence[Callable[[], Any]], device: torch.device, repeats: int, warmup: int
) -> list[float]:
    """Median wall-clock seconds of each `fn()` over `repeats` runs after `warmup` untimed ones.

    The functions are timed round-robin (a, b, a, b, ...), so a load change on a shared machine affects
    all of them alike and their ratio (e.g. KPCN / its network alone) stays meaningful."""
    for fn in fns:
        for _ in range(warmup):
            fn()
    _sync(device)
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for fn, samples in zip(fns, times, strict=True):
            start = time.perf_counter()
            fn()
            _sync(device)
            samples.append(time.perf_counter() - start)
    return [statistics.median(samples) for samples in times]


class NetworkOnly(nn.Module):
    """A kernel model's networks without `apply_kernel` (same tiles, same halo): the "conv stack alone"
    that the kernel-application overhead is measured against."""

    learned = True

    def __init__(self, model: TwoBranchDenoiser) -> None:
        super().__init__()
        self.model = model

    @property
    def halo(self) -> int:
        return self.model.halo

    def forward(self, batch: Mapping[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        return self.model.network_outputs(batch)


def _tiles(size: int, tile: int) -> list[slice]:
    step = size if tile <= 0 else tile
    return [slice(start, min(start + step, size)) for start in range(0, size, step)]


def conv_baseline(height: int, width: int, tile: int, device: torch.device, timer) -> Row:
    """F.conv2d 100 -> 100, 5x5, 'same' padding over the frame in the same tiles (no halo)."""
    c, k = BASELINE_CONV["channels"], BASELINE_CONV["kernel"]
    x = torch.randn(1, c, height, width, device=device)
    weight = torch.randn(c, c, k, k, device=device) / (c * k * k) ** 0.5
    bias = torch.zeros(c, device=device)

    def run() -> None:
        for ys in _tiles(height, tile):
            for xs in _tiles(width, tile):
                F.conv2d(x[..., ys, xs], weight, bias, padding=k // 2)

    name = f"conv2d {c}->{c} {k}x{k}"
    return Row(name, timer([run])[0], flops_per_pixel=2.0 * c * c * k * k, note="plain F.conv2d, reference")


def bench_model(name: str, cfg: Mapping[str, Any], batch, tile: int, device: torch.device, timer, seed: int):
    """Rows for one model: itself, and for kernel models its networks alone (timed interleaved)."""
    torch.manual_seed(seed)
    model: Denoiser = build_denoiser(cfg).to(device).eval()
    flops = flops_per_pixel(model)
    params = count_parameters(model)
    runs = [lambda: infer_tiled(model, batch, tile)]
    if isinstance(model, TwoBranchDenoiser) and model.output == "kernel":
        net = NetworkOnly(model)
        runs.append(lambda: infer_tiled(net, batch, tile))
    seconds = timer(runs)
    note = ", ".join(f"{key} {cfg[key]}" for key in ("architecture", "output") if key in cfg)
    rows = [Row(name, seconds[0], flops["total"], params, note)]
    if len(seconds) > 1:
        rows.append(Row(f"{name} (net only)", seconds[1], flops["conv"], params, "no apply_kernel"))
    return rows


def bench_oidn(profile: str, batch, timer) -> Row:
    """OIDN on the full frame (it is never tiled), or a row saying why it cannot run here."""
    try:
        model = build_denoiser(load_model_config("oidn", profile))
        seconds = timer([lambda: infer_tiled(model, batch, 0)])[0]
        return Row("oidn", seconds, note="pyoidn, full frame")
    except Exception as err:  # import failure, missing native library, unsupported device...
        reason = " ".join(str(err).split()) or type(err).__name__
        return Row("oidn", None, note=f"unavailable ({reason})")


def _fmt(x: float | None, spec: str) -> str:
    return "n/a" if x is None else format(x, spec)


def format_table(rows: Sequence[Row], pixels: int, baseline: Row) -> str:
    """Fixed-width table: per frame, per megapixel, FLOPs, throughput and its share of the conv2d rate."""
    base_rate = baseline.flops_per_pixel * pixels / baseline.seconds
    header = ("model", "params", "GFLOP/frame", "s/frame", "s/MPix", "GFLOP/s", "% conv2d", "note")
    lines = [header]
    for r in rows:
        gflop = None if r.flops_per_pixel is None else r.flops_per_pixel * pixels / 1e9
        rate = None if gflop is None or r.seconds is None else gflop / r.seconds
        lines.append(
            (
                r.name,
                "-" if r.params is None else f"{r.params:,}",
                _fmt(gflop, ",.2f"),
                _fmt(r.seconds, ".4f"),
                _fmt(None if r.seconds is None else r.seconds / (pixels / 1e6), ".4f"),
                _fmt(rate, ",.1f"),
                _fmt(None if rate is None else 100 * rate * 1e9 / base_rate, ".0f"),
                r.note,
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join(_format_line(line, widths) for line in lines)


def _format_line(cells: Sequence[str], widths: Sequence[int]) -> str:
    """Name left-aligned, numbers right-aligned, the note last and unpadded."""
    name, *numbers, note = cells
    padded = [name.ljust(widths[0])] + [c.rjust(w) for c, w in zip(numbers, widths[1:-1], strict=True)]
    return "  ".join([*padded, note]).rstrip()


def _ratio(a: Row | None, b: Row | None, attr: str) -> str:
    x, y = (getattr(a, attr, None), getattr(b, attr, None)) if a and b else (None, None)
    return "n/a" if not x or not y else f"{x / y:.2f}x"


def format_ratios(by_name: Mapping[str, Row]) -> list[str]:
    kpcn, dpcn = by_name.get("kpcn"), by_name.get("dpcn")
    lines = [
        "ratios:",
        f"  KPCN / DPCN time:  {_ratio(kpcn, dpcn, 'seconds')}   "
        f"(FLOP ratio KPCN / DPCN: {_ratio(kpcn, dpcn, 'flops_per_pixel')}, "
        "from the 441-channel kernel output layer vs 3 channels)",
    ]
    for name, row in by_name.items():
        net = by_name.get(f"{name} (net only)")
        if net is not None:
            lines.append(
                f"  kernel-application overhead, {name} total / {name} net only (equal backbone): "
                f"{_ratio(row, net, 'seconds')}   "
                f"(target <= ~1.2x; FLOP ratio {_ratio(row, net, 'flops_per_pixel')})"
            )
    return lines


def _header(args, device: torch.device, tile: int) -> str:
    if device.type == "cuda":
        where = torch.cuda.get_device_name(device)
    else:
        where = f"{torch.get_num_threads()} threads"
    tiling = "whole frame" if tile <= 0 else f"{tile}x{tile} tiles + halo"
    return (
        f"denoise benchmark: {args.width}x{args.height} frame, profile {args.profile}, device {device} "
        f"({where}), {tiling}, median of {args.repeats} after {args.warmup} warm-up, "
        f"autocast {args.autocast}, torch {torch.__version__}"
    )


def run_denoise(args: argparse.Namespace) -> str:
    """All measurements of `denoise`; returns the printed report."""
    device = _device(args.device)
    tile = args.tile if args.tile is not None else (0 if device.type == "cuda" else CPU_TILE)
    dtype = AUTOCAST_DTYPES[args.autocast]
    autocast = torch.autocast(device.type, dtype=dtype) if dtype is not None else nullcontext()
    generator = torch.Generator().manual_seed(args.seed)
    batch = random_batch(args.height, args.width, generator=generator, device=device)

    def timer(fns):
        return time_calls(fns, device, args.repeats, args.warmup)

    rows: list[Row] = []
    with torch.inference_mode(), autocast:
        for name in [m.strip() for m in args.models.split(",") if m.strip()]:
            rows += bench_model(
                name, load_model_config(name, args.profile), batch, tile, device, timer, args.seed
            )
        if args.oidn:
            rows.append(bench_oidn(args.profile, batch, timer))
        baseline = conv_baseline(args.height, args.width, tile, device, timer)
    rows.append(baseline)
    pixels = args.width * args.height
    by_name = {r.name: r for r in rows}
    return "\n".join(
        [_header(args, device, tile), format_table(rows, pixels, baseline), *format_ratios(by_name)]
    )


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m src.bench", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    d = commands.add_parser("denoise", help="inference time of the learned denoisers, OIDN and conv2d")
    d.add_argument("--width", type=int, default=1280, help="frame width (default: the KPCN set's 1280)")
    d.add_argument("--height", type=int, default=720, help="frame height (default 720)")
    d.add_argument("--repeats", type=int, default=3, help="timed runs per model (median reported)")
    d.add_argument("--warmup", type=int, default=1, help="untimed runs first (allocator, cuDNN autotune)")
    d.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU) | cpu | cuda | cuda:N")
    d.add_argument("--models", default="dpcn,kpcn,resnet", help="comma-separated conf/model names")
    d.add_argument(
        "--profile", default="paper", help="profile whose model sizes are used (paper: Bako et al.)"
    )
    d.add_argument(
        "--tile", type=int, default=None, help=f"tile side; 0 = whole frame (default: CPU {CPU_TILE})"
    )
    d.add_argument("--autocast", choices=sorted(AUTOCAST_DTYPES), default="none", help="mixed precision")
    d.add_argument("--oidn", action=argparse.BooleanOptionalAction, default=True, help="also time OIDN")
    d.add_argument("--seed", type=int, default=0, help="seed of the random weights and inputs")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if min(args.width, args.height, args.repeats) < 1 or args.warmup < 0:
        print("bench: --width, --height and --repeats must be >= 1, --warmup >= 0", file=sys.stderr)
        return 2
    try:
        print(run_denoise(args))
    except (NrbenchError, HydraException) as err:  # a bad config value or an unknown model name
        print(f"bench: {' '.join(str(err).split())}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
