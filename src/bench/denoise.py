"""``python -m src.bench denoise``: times full-frame inference of the learned denoisers (random weights,
seeded; random inputs: speed does not depend on the values) and prints, in one run:
- each model's seconds per frame and per megapixel, its conv depth (layers on the longest input-to-output
  path), FLOPs and achieved GFLOP/s, and the spread of its time over the rounds;
- KPCN/DPCN time and FLOP ratios (the FLOP ratio ~1.6 comes from KPCN's 441-channel output layer);
- the kernel-application overhead: a kernel model's total time / the same network without
  `apply_kernel` ("at equal backbone, KPCN costs <= ~1.2x": the Bako et al. 2017 claim that applying the
  kernel is cheap; a per-pixel Python loop in the seed thesis took 140 s per frame);
- OIDN on the same frame and device, if `pyoidn` works here;
- the claims of the U-Net KPCN of the sequences' radiance branch (`unet_kpcn`, Zhu et al. 2023: >= 10x
  faster than KPCN, within 2x of OIDN) as per-round time ratios against both KPCN forms (`kpcn`, Bako et
  al.'s two-branch still-image KPCN, and `kpcn_frame`, the one-branch KPCN on the sequences' radiance
  that the `unet_vs_kpcn` study trains per frame) and OIDN; each model reads a random frame of its own
  branches and `in_channels` (`dataset.volume_features` of the profile for the sequences' models);
- a plain `F.conv2d` (100 -> 100 channels, 5x5, the DPCN hidden layer) on the same frame, as the
  achievable conv throughput of this device.

Timing: after `--warmup` untimed calls of each, `--rounds` rounds each time every row once, in an order
that rotates between rounds (`src.bench.timing.round_order`, a Williams design), so a load change on a
shared machine hits the models of a round alike and no model always runs first or after the same one. A
model's time is its median over the rounds (with the interquartile range and range); a ratio of two
models is taken per round (the same load) and reported as the median and range of those ratios. At
least 5 rounds (7 by default): a two-sided Wilcoxon signed-rank test over n rounds cannot go below
p = 2 / 2^n, 0.0625 with 5 and 0.016 with 7.

Frames are processed in tiles (plus each model's halo, so results equal a full-frame pass) to bound
memory; on CUDA the default is the whole frame at once. GFLOP/s counts the useful FLOPs of one frame
(`flops_per_pixel` x pixels): work redone in tile halos shows up as lower throughput, not more FLOPs.

`--log` records the run in MLflow (`src.bench.bench_log`): experiment `nrbench-bench`, the medians as
metrics `seconds_<model>` and every timing as the artifact `bench/rounds.csv` (round, model, seconds).
"""

from __future__ import annotations

import argparse
from contextlib import contextmanager, nullcontext

import torch

from src.bench.denoise_table import format_claims, format_ratios, format_spreads, format_table
from src.bench.denoise_timing import Prepared, bench_model, bench_oidn, timed_rows
from src.bench.peak import conv_baseline
from src.bench.timing import device_name, time_rounds
from src.data.features import PAPER_CHANNELS
from src.models.denoise.models import BRANCHES
from src.models.denoise.summary import random_batch
from src.tracking.peak_memory import PeakMemory
from src.train.device import device_card, precision

#: Tile side on CPU (pixels, before the halo): bounds activation memory at paper width.
CPU_TILE = 256
AUTOCAST_DTYPES = {"none": None, "bf16": torch.bfloat16, "fp16": torch.float16}
#: Fewest `--rounds`: with 5, a two-sided Wilcoxon signed-rank test over rounds reaches p = 0.0625 at best.
MIN_ROUNDS = 5


def _device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


@contextmanager
def tf32_mode(mode: str):
    """PyTorch's TF32 flags for the block (`--tf32`): `default` leaves them, `on` / `off` sets both the
    convolutions' and the matmuls'; restored after."""
    saved = (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32)
    if mode != "default":
        torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = mode == "on"
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def bench_precision(args, device: torch.device) -> str:
    """The arithmetic the bench ran in, as runs state it (`src.train.device.precision`, under `--tf32`)."""
    if args.autocast != "none":  # the bench autocasts on the CPU too (training does only on CUDA)
        return f"{args.autocast}-autocast"
    with tf32_mode(args.tf32):
        return precision(False, device)


def _header(args, device: torch.device, tile: int) -> str:
    tiling = "whole frame" if tile <= 0 else f"{tile}x{tile} tiles + halo"
    return (
        f"denoise benchmark: {args.width}x{args.height} frame, profile {args.profile}, device {device} "
        f"({device_name(device)}), {tiling}, median of {args.rounds} rounds after {args.warmup} warm-up, "
        f"precision {bench_precision(args, device)}, torch {torch.__version__}; the clock covers each "
        "model's forward pass over the frame (inputs already on the device, no transfers)"
    )


def _prepare(args, device: torch.device, tile: int) -> list[Prepared]:
    """Every row of the table with the function it times: the models (and kernel models' networks
    alone), OIDN, and the reference conv2d."""
    generator = torch.Generator().manual_seed(args.seed)
    still = random_batch(args.height, args.width, generator=generator, device=device)
    batches = {(BRANCHES, len(PAPER_CHANNELS)): still}
    prepared: list[Prepared] = []
    size = (args.height, args.width)
    for name in [m.strip() for m in args.models.split(",") if m.strip()]:
        prepared += bench_model(name, args.profile, batches, size, tile, device, args.seed)
    if args.oidn:
        prepared.append(bench_oidn(args.profile, still, device))
    prepared.append(conv_baseline(args.height, args.width, tile, device))
    return prepared


def run_denoise(args: argparse.Namespace) -> str:
    """All measurements of `denoise`; returns the report to print, or with `--log` prints it, logs the run
    and returns the line naming the run."""
    device = _device(args.device)
    tile = args.tile if args.tile is not None else (0 if device.type == "cuda" else CPU_TILE)
    dtype = AUTOCAST_DTYPES[args.autocast]
    autocast = torch.autocast(device.type, dtype=dtype) if dtype is not None else nullcontext()
    with PeakMemory() as peak, tf32_mode(args.tf32), torch.inference_mode(), autocast:
        prepared = _prepare(args, device, tile)
        timed = {row.key: run for row, run in prepared if run is not None}
        rounds = time_rounds(timed, device, args.rounds, args.warmup)
    rows = timed_rows(prepared, rounds)
    by_key = {r.key: r for r in rows}
    report = "\n".join(
        [
            _header(args, device, tile),
            format_table(rows, args.width * args.height, by_key["conv2d"]),
            format_spreads(rows, args.rounds, args.warmup),
            *format_ratios(by_key, rounds),
            *format_claims(by_key, rounds),
            _memory_line(peak),
        ]
    )
    if not args.log:
        return report
    print(report, flush=True)  # before logging: a store that cannot be used must not lose the measurement
    from src.bench.bench_log import log_bench_run  # MLflow: imported only to log

    run_id = log_bench_run("denoise", _params(args, device, tile), _tags(args, device), rows, rounds, report)
    return f"logged: MLflow run {run_id} in experiment nrbench-bench (artifact bench/rounds.csv)"


def _memory_line(peak: PeakMemory) -> str:
    """The bench's peak memory, every model together (host: sampled resident set; GPU: PyTorch's
    allocator, OIDN's own buffers not in it)."""
    device = "" if peak.device_mb is None else f", GPU {peak.device_mb:,.0f} MB (PyTorch allocator)"
    return f"peak memory: host {peak.host_mb:,.0f} MB{device}"


def _params(args, device: torch.device, tile: int) -> dict[str, object]:
    keys = ("width", "height", "rounds", "warmup", "profile", "models", "autocast", "tf32", "seed", "oidn")
    return {"bench": "denoise", **{k: getattr(args, k) for k in keys}, "device": str(device), "tile": tile}


def _tags(args, device: torch.device) -> dict[str, str]:
    return {
        "nrbench.profile": args.profile,
        "nrbench.device": str(device),
        # as runs tag it (the report matches a run's device and precision to the peak measured here)
        **{f"nrbench.{key}": value for key, value in device_card(device).items()},
        "nrbench.precision": bench_precision(args, device),
        "nrbench.torch": torch.__version__,
    }
