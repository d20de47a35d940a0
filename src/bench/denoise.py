"""``python -m src.bench denoise``: times full-frame inference of the learned denoisers (random weights,
seeded; random inputs: speed does not depend on the values) and prints, in one run:
- each model's seconds per frame and per megapixel, FLOPs and achieved GFLOP/s;
- KPCN/DPCN time and FLOP ratios (the FLOP ratio ~1.6 comes from KPCN's 441-channel output layer);
- the kernel-application overhead: a kernel model's total time / the same network without
  `apply_kernel` ("at equal backbone, KPCN costs <= ~1.2x": the Bako et al. 2017 claim that applying the
  kernel is cheap; a per-pixel Python loop in the seed thesis took 140 s per frame);
- OIDN on the same frame, if `pyoidn` works here;
- the U-Net KPCN of the sequences' radiance branch (`unet_kpcn`, timed on a random batch of that branch
  with its profile's `in_channels`) against KPCN and OIDN (the targets: >= 10x faster than KPCN, within
  2x of OIDN);
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
from contextlib import nullcontext

import torch

from src.bench.denoise_table import format_ratios, format_table
from src.bench.denoise_timing import Row, bench_model, bench_oidn
from src.bench.model_configs import load_model_config
from src.bench.peak import conv_baseline
from src.bench.timing import device_name, time_calls
from src.models.denoise.summary import random_batch

#: Tile side on CPU (pixels, before the halo): bounds activation memory at paper width.
CPU_TILE = 256
AUTOCAST_DTYPES = {"none": None, "bf16": torch.bfloat16, "fp16": torch.float16}


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


def _header(args, device: torch.device, tile: int) -> str:
    tiling = "whole frame" if tile <= 0 else f"{tile}x{tile} tiles + halo"
    return (
        f"denoise benchmark: {args.width}x{args.height} frame, profile {args.profile}, device {device} "
        f"({device_name(device)}), {tiling}, median of {args.repeats} after {args.warmup} warm-up, "
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
