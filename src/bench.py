"""Benchmarks: ``python -m src.bench denoise [--width 1280 --height 720 --repeats 3 --device auto
--models dpcn,kpcn,resnet --profile paper]`` and ``python -m src.bench nerf [--models nerf,mipnerf,refnerf
--profile cpu --batch 1024 --steps 5 --render-rays 4096 --chunk 4096 --device auto]``.

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

`nerf` times the NeRF-family models (random weights, seeded) as ``python -m src.run task=nerf
model=<name> profile=<profile>`` builds them, and prints per model: parameters, MLP forward FLOPs per ray
(`nerf_mlp_flops_per_ray`), training rays/s (Adam steps on one random batch of `--batch` rays, loss,
backward and optimiser step included; one untimed warm-up step, then the median of `--steps` timed
ones, so that a load spike on a shared machine does not decide it), rendering
rays/s (`render_rays_chunked` on `--render-rays` rays; one untimed warm-up pass, then one timed pass),
each model's time per ray relative to the first model's (measured in the same run) and the achieved
GFLOP/s (a training step counted as 3 x the forward FLOPs, rendering as 1 x). The rays are those of
one camera on a sphere of radius 4 looking at the origin, on [2, 6] (the Blender scenes' setting).
"""

from __future__ import annotations

import argparse
import math
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

from src.data.blender import focal_from_fov, generate_rays
from src.errors import ConfigError, NrbenchError, one_line
from src.models.denoise.base import Denoiser
from src.models.denoise.models import TwoBranchDenoiser, infer_tiled
from src.models.denoise.summary import count_parameters, flops_per_pixel, random_batch
from src.models.instantiate import build_method
from src.models.nerf.inference import render_rays_chunked
from src.models.nerf.models import NerfModelBase, RefNeRF
from src.models.nerf.summary import nerf_mlp_flops_per_ray
from src.render.multiview import look_at_c2w, sphere_position
from src.train.device import pick_device, seed_everything

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
#: Tile side on CPU (pixels, before the halo): bounds activation memory at paper width.
CPU_TILE = 256
#: The reference convolution: the DPCN/KPCN hidden layer of Bako et al. 2017 (100 -> 100 channels, 5x5).
BASELINE_CONV = {"channels": 100, "kernel": 5}
AUTOCAST_DTYPES = {"none": None, "bf16": torch.bfloat16, "fp16": torch.float16}
#: The `nerf` rays: one camera at this distance from the origin, looking at it (the Blender scenes' setup:
#: conf/dataset/nerf_procedural.yaml radius, elevation of its test circle, field of view, near and far).
NERF_CAMERA = {"radius": 4.0, "elevation_deg": 30.0, "azimuth_deg": 0.0, "camera_angle_x": 0.6911112070083618}
NERF_NEAR, NERF_FAR = 2.0, 6.0
#: Forward-FLOP multiplier of a training step (forward + backward ~ 2 x forward) and of rendering.
TRAIN_FLOP_FACTOR, RENDER_FLOP_FACTOR = 3, 1


@dataclass
class Row:
    """One line of the result table."""

    name: str
    seconds: float | None  # median seconds per frame
    flops_per_pixel: float | None = None
    params: int | None = None
    note: str = ""


def load_model_config(name: str, profile: str, task: str | None = None) -> dict[str, Any]:
    """The `model:` group as `python -m src.run [task=<task>] model=<name> profile=<profile>` composes it
    (conf/model_profile/<name>_<profile>.yaml included; `task=nerf` also sets the NeRF dataset that
    `model.background` refers to)."""
    overrides = ([f"task={task}"] if task else []) + [f"model={name}", f"profile={profile}"]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        cfg = compose("config", overrides=overrides)
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
    model: Denoiser = build_method(cfg).to(device).eval()
    flops = flops_per_pixel(model)
    params = count_parameters(model)
    runs = [lambda: infer_tiled(model, batch, tile)]
    if isinstance(model, TwoBranchDenoiser) and model.output == "kernel":
        net = NetworkOnly(model)
        runs.append(lambda: infer_tiled(net, batch, tile))
    seconds = timer(runs)
    note = cfg["_target_"].rsplit(".", 1)[-1] + (f", output {cfg['output']}" if "output" in cfg else "")
    rows = [Row(name, seconds[0], flops["total"], params, note)]
    if len(seconds) > 1:
        rows.append(Row(f"{name} (net only)", seconds[1], flops["conv"], params, "no apply_kernel"))
    return rows


def bench_oidn(profile: str, batch, timer) -> Row:
    """OIDN on the full frame (it is never tiled), or a row saying why it cannot run here."""
    try:
        model = build_method(load_model_config("oidn", profile))
        seconds = timer([lambda: infer_tiled(model, batch, 0)])[0]
        return Row("oidn", seconds, note="pyoidn, full frame")
    except Exception as err:  # import failure, missing native library, unsupported device...
        reason = one_line(err)
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


def _where(device: torch.device) -> str:
    """The GPU's name, or the CPU thread count torch uses."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"{torch.get_num_threads()} threads"


def _header(args, device: torch.device, tile: int) -> str:
    tiling = "whole frame" if tile <= 0 else f"{tile}x{tile} tiles + halo"
    return (
        f"denoise benchmark: {args.width}x{args.height} frame, profile {args.profile}, device {device} "
        f"({_where(device)}), {tiling}, median of {args.repeats} after {args.warmup} warm-up, "
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


# --- nerf ----------------------------------------------------------------------------------------------


@dataclass
class NerfRow:
    """One model's measurements."""

    name: str
    params: int
    flops_per_ray: int  # MLP forward FLOPs per ray, coarse + fine
    train_seconds: float  # median seconds of one step of `train_rays` rays
    train_rays: int
    render_seconds: float  # seconds of one pass over `render_rays` rays
    render_rays: int
    note: str = ""

    @property
    def train_seconds_per_ray(self) -> float:
        return self.train_seconds / self.train_rays

    @property
    def render_seconds_per_ray(self) -> float:
        return self.render_seconds / self.render_rays


def nerf_model_names() -> list[str]:
    """The radiance fields `nerf` can time: the conf/model configs of `family: nerf`, a user's included."""
    return sorted(
        p.stem for p in (CONF_DIR / "model").glob("*.yaml") if OmegaConf.load(p).get("family") == "nerf"
    )


def parse_model_names(models: str) -> list[str]:
    """The comma-separated `--models` list; an unknown or missing name is a one-line `ConfigError`."""
    names = [m.strip() for m in models.split(",") if m.strip()]
    nerf_models = nerf_model_names()
    expected = f"expected one of {nerf_models}"
    if not names:
        raise ConfigError(f"--models: no model named in {models!r}; {expected}")
    for name in names:
        if name not in nerf_models:
            raise ConfigError(f"--models: unknown NeRF model {name!r}; {expected}")
    return names


def nerf_model_configs(models: str, profile: str) -> dict[str, dict[str, Any]]:
    """{name: model config} for the `--models` list, composed as `python -m src.run task=nerf
    model=<name> profile=<profile>`, all before anything is timed (a bad name or profile fails at once)."""
    return {name: load_model_config(name, profile, task="nerf") for name in parse_model_names(models)}


def benchmark_rays(
    n: int, generator: torch.Generator, device: torch.device, shuffle: bool
) -> dict[str, torch.Tensor]:
    """`n` rays (`RAY_KEYS`) of one camera on a sphere of radius 4 looking at the origin, near 2, far 6:
    the pixels of a square image just large enough, in image order or (`shuffle`) a random subset."""
    side = max(2, math.isqrt(n - 1) + 1)  # side * side >= n
    cam = NERF_CAMERA
    position = sphere_position(
        cam["radius"], math.radians(cam["elevation_deg"]), math.radians(cam["azimuth_deg"])
    )
    c2w = look_at_c2w(position)
    rays = generate_rays(c2w, focal_from_fov(cam["camera_angle_x"], side), side, side, NERF_NEAR, NERF_FAR)
    pick = torch.randperm(side * side, generator=generator)[:n] if shuffle else torch.arange(n)
    return {key: value[pick].to(device) for key, value in rays.items()}


def time_runs(fn: Callable[[], Any], device: torch.device, runs: int, warmup: int = 1) -> float:
    """Median wall-clock seconds of `runs` calls of `fn()` after `warmup` untimed ones, each call
    synchronised (a median, so a load spike on a shared machine does not decide the result)."""
    return time_calls([fn], device, runs, warmup)[0]


def train_step_fn(
    model: NerfModelBase, rays: Mapping[str, torch.Tensor], target: torch.Tensor, lr: float = 5e-4
) -> Callable[[], None]:
    """One training step on a fixed ray batch, as `NerfTrainer.train_step` does it: stratified (jittered)
    samples, the model's loss, backward, Adam step."""
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)

    def step() -> None:
        loss, _ = model.loss(model(rays, randomized=True), target)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    return step


def time_training(
    model: NerfModelBase,
    rays: Mapping[str, torch.Tensor],
    target: torch.Tensor,
    steps: int,
    device: torch.device,
) -> float:
    """Median seconds of one training step on `rays` over `steps` steps (after one untimed warm-up)."""
    return time_runs(train_step_fn(model, rays, target), device, steps)


def time_rendering(
    model: NerfModelBase, rays: Mapping[str, torch.Tensor], chunk: int, device: torch.device
) -> float:
    """Seconds of one `render_rays_chunked` pass over `rays` (after one untimed warm-up pass)."""
    model.eval()
    return time_runs(lambda: render_rays_chunked(model, rays, chunk), device, 1)


def bench_nerf_model(
    name: str,
    cfg: Mapping[str, Any],
    train_rays: Mapping[str, torch.Tensor],
    target: torch.Tensor,
    render_rays: Mapping[str, torch.Tensor],
    args: argparse.Namespace,
    device: torch.device,
) -> NerfRow:
    """Build `name` (seeded), then time its training steps and its rendering."""
    torch.manual_seed(args.seed)
    model = build_method(cfg).to(device)
    coarse, fine = model.samples_per_level()
    note = f"{coarse}+{fine} samples"
    if isinstance(model, RefNeRF):
        note += "; FLOPs exclude the normals' density gradient"
    n_train, n_render = train_rays["origins"].shape[0], render_rays["origins"].shape[0]
    train_seconds = time_training(model, train_rays, target, args.steps, device)
    render_seconds = time_rendering(model, render_rays, args.chunk, device)
    return NerfRow(
        name,
        count_parameters(model),
        nerf_mlp_flops_per_ray(model)["total"],
        train_seconds,
        n_train,
        render_seconds,
        n_render,
        note,
    )


def format_nerf_table(rows: Sequence[NerfRow]) -> str:
    """Fixed-width table; the ratios are time per ray over the first row's (so that row reads 1.00)."""
    first = rows[0]
    header = (
        "model",
        "params",
        "FLOP/ray",
        "train rays/s",
        "train ratio",
        "train GFLOP/s",
        "render rays/s",
        "render ratio",
        "render GFLOP/s",
        "note",
    )
    lines = [header]
    for r in rows:
        train_rate, render_rate = 1 / r.train_seconds_per_ray, 1 / r.render_seconds_per_ray
        lines.append(
            (
                r.name,
                f"{r.params:,}",
                f"{r.flops_per_ray:,}",
                f"{train_rate:,.0f}",
                f"{r.train_seconds_per_ray / first.train_seconds_per_ray:.2f}",
                f"{TRAIN_FLOP_FACTOR * r.flops_per_ray * train_rate / 1e9:,.2f}",
                f"{render_rate:,.0f}",
                f"{r.render_seconds_per_ray / first.render_seconds_per_ray:.2f}",
                f"{RENDER_FLOP_FACTOR * r.flops_per_ray * render_rate / 1e9:,.2f}",
                r.note,
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join(_format_line(line, widths) for line in lines)


def nerf_footnotes(first: str) -> list[str]:
    return [
        "FLOP/ray: MLP forward FLOPs per ray (2 x MACs of every nn.Linear, coarse + fine samples; "
        "encodings and volume rendering not counted).",
        f"ratio: the model's time per ray / {first}'s (the first model, measured in this run).",
        f"GFLOP/s: FLOP/ray x rays/s, counting a training step as {TRAIN_FLOP_FACTOR} x the forward FLOPs "
        f"(forward + backward) and rendering as {RENDER_FLOP_FACTOR} x.",
    ]


def _nerf_header(args, device: torch.device) -> str:
    return (
        f"nerf benchmark: profile {args.profile}, device {device} ({_where(device)}), seed {args.seed}, "
        f"torch {torch.__version__}; train: median of {args.steps} Adam steps of {args.batch} rays "
        f"after 1 warm-up; render: {args.render_rays} rays in chunks of {args.chunk}, 1 timed pass "
        "after 1 warm-up"
    )


def run_nerf(args: argparse.Namespace) -> str:
    """All measurements of `nerf`; returns the printed report (progress goes to stderr)."""
    device = pick_device(args.device)
    configs = nerf_model_configs(args.models, args.profile)
    seed_everything(args.seed)
    generator = torch.Generator().manual_seed(args.seed)
    train_rays = benchmark_rays(args.batch, generator, device, shuffle=True)
    target = torch.rand(args.batch, 3, generator=generator).to(device)
    render_rays = benchmark_rays(args.render_rays, generator, device, shuffle=False)
    rows = []
    for i, (name, cfg) in enumerate(configs.items(), start=1):
        print(f"[{i}/{len(configs)}] {name}: training, then rendering ...", file=sys.stderr, flush=True)
        rows.append(bench_nerf_model(name, cfg, train_rays, target, render_rays, args, device))
    return "\n".join([_nerf_header(args, device), format_nerf_table(rows), *nerf_footnotes(rows[0].name)])


def _check_denoise(args: argparse.Namespace) -> str | None:
    if min(args.width, args.height, args.repeats) < 1 or args.warmup < 0:
        return "--width, --height and --repeats must be >= 1, --warmup >= 0"
    return None


def _check_nerf(args: argparse.Namespace) -> str | None:
    if min(args.batch, args.steps, args.render_rays, args.chunk) < 1:
        return "--batch, --steps, --render-rays and --chunk must be >= 1"
    return None


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
    d.set_defaults(run=run_denoise, check=_check_denoise)

    n = commands.add_parser("nerf", help="training and rendering rays/s of NeRF, mip-NeRF and Ref-NeRF")
    n.add_argument("--models", default="nerf,mipnerf,refnerf", help="comma-separated; the first is the peer")
    n.add_argument(
        "--profile", default="cpu", help="cpu (default, as in src.run) | smoke | paper (published sizes: GPU)"
    )
    n.add_argument("--batch", type=int, default=1024, help="rays per training step")
    n.add_argument("--steps", type=int, default=5, help="timed training steps (median; after 1 untimed)")
    n.add_argument(
        "--render-rays", type=int, default=4096, help="rays rendered (1 timed pass after 1 untimed)"
    )
    n.add_argument("--chunk", type=int, default=4096, help="rays per forward pass when rendering")
    n.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU) | cpu | cuda")
    n.add_argument("--seed", type=int, default=0, help="seed of the random weights, rays and samples")
    n.set_defaults(run=run_nerf, check=_check_nerf)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    problem = args.check(args)
    if problem:
        print(f"bench: {problem}", file=sys.stderr)
        return 2
    try:
        print(args.run(args))
    except (NrbenchError, HydraException) as err:  # a bad config value or an unknown model name
        print(f"bench: {one_line(err)}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
