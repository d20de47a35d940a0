"""``python -m src.bench nerf``: times the NeRF-family models (random weights, seeded) as ``python -m src.run
task=nerf model=<name> profile=<profile>`` builds them, and prints per model: parameters, MLP forward FLOPs
per ray (`nerf_mlp_flops_per_ray`), training rays/s (Adam steps on one random batch of `--batch` rays, loss,
backward and optimiser step included; one untimed warm-up step, then the median of `--steps` timed
ones, so that a load spike on a shared machine does not decide it), rendering
rays/s (`render_rays_chunked` on `--render-rays` rays; one untimed warm-up pass, then one timed pass),
each model's time per ray relative to the first model's (measured in the same run) and the achieved
GFLOP/s (a training step counted as 3 x the forward FLOPs, rendering as 1 x). The rays are those of
one camera on a sphere of radius 4 looking at the origin, on [2, 6] (the Blender scenes' setting): the
first test pose of `task=nerf profile=<profile>`'s dataset (`BenchCamera.from_dataset`).
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

import torch
from omegaconf import OmegaConf

from src.bench.model_configs import CONF_DIR, load_dataset_config, load_model_config
from src.bench.nerf_table import format_nerf_table, nerf_footnotes
from src.bench.nerf_timing import BenchCamera, bench_nerf_model, benchmark_rays
from src.bench.timing import device_name
from src.errors import ConfigError
from src.train.device import pick_device, seed_everything


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


def _nerf_header(args, device: torch.device) -> str:
    return (
        f"nerf benchmark: profile {args.profile}, device {device} ({device_name(device)}), seed {args.seed}, "
        f"torch {torch.__version__}; train: median of {args.steps} Adam steps of {args.batch} rays "
        f"after 1 warm-up; render: {args.render_rays} rays in chunks of {args.chunk}, 1 timed pass "
        "after 1 warm-up"
    )


def run_nerf(args: argparse.Namespace) -> str:
    """All measurements of `nerf`; returns the printed report (progress goes to stderr)."""
    device = pick_device(args.device)
    configs = nerf_model_configs(args.models, args.profile)
    camera = BenchCamera.from_dataset(load_dataset_config("nerf", args.profile))
    seed_everything(args.seed)
    generator = torch.Generator().manual_seed(args.seed)
    train_rays = benchmark_rays(args.batch, generator, device, shuffle=True, camera=camera)
    target = torch.rand(args.batch, 3, generator=generator).to(device)
    render_rays = benchmark_rays(args.render_rays, generator, device, shuffle=False, camera=camera)
    rows = []
    for i, (name, cfg) in enumerate(configs.items(), start=1):
        print(f"[{i}/{len(configs)}] {name}: training, then rendering ...", file=sys.stderr, flush=True)
        rows.append(bench_nerf_model(name, cfg, train_rays, target, render_rays, args, device))
    return "\n".join([_nerf_header(args, device), format_nerf_table(rows), *nerf_footnotes(rows[0].name)])
