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
import os
import sys
from typing import Any

import torch
from omegaconf import OmegaConf

from src.bench.model_configs import CONF_DIR, load_dataset_config, load_model_config, load_task_config
from src.bench.nerf_peer import NerfPytorchStep, load_nerf_pytorch
from src.bench.nerf_table import (
    REFNERF_WITHOUT_NORMALS,
    format_nerf_table,
    nerf_footnotes,
    nerf_ratio_lines,
)
from src.bench.nerf_timing import (
    BenchCamera,
    NerfRow,
    benchmark_rays,
    matmul_reference,
    model_row,
    time_rendering,
    train_step_fn,
)
from src.bench.timing import device_name, time_calls
from src.errors import ConfigError
from src.models.instantiate import build_method
from src.train.device import pick_device, seed_everything
from src.train.nerf_trainer import micro_batch_rays, render_chunk

#: Width of the matmul reference (the NeRF-family MLPs' 256 channels).
MATMUL_WIDTH = 256
#: `--autocast` of the training steps: fp32 or bf16 autocast as `task.train.amp` (fp16 would need loss
#: scaling, which training does not do).
NERF_AUTOCAST_DTYPES = {"none": None, "bf16": torch.bfloat16}


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
    model=<name> profile=<profile>`, all before anything is timed (a bad name or profile fails at once).
    With both mipnerf and refnerf listed, Ref-NeRF is timed a second time without its density-gradient
    normals (`density_normals: false`, so also without R_p), which splits its cost over mip-NeRF's into
    the normals' share and the rest (its directional MLP)."""
    configs = {name: load_model_config(name, profile, task="nerf") for name in parse_model_names(models)}
    if {"mipnerf", "refnerf"} <= configs.keys():
        configs[REFNERF_WITHOUT_NORMALS] = {
            **configs["refnerf"],
            "density_normals": False,
            "pred_normal_loss_mult": 0.0,
        }
    return configs


def _nerf_header(args, device: torch.device, micro: int | None) -> str:
    split = "whole batch" if micro is None else f"micro-batches of {micro} rays"
    return (
        f"nerf benchmark: profile {args.profile}, device {device} ({device_name(device)}, OMP_WAIT_POLICY "
        f"{os.environ.get('OMP_WAIT_POLICY', 'unset')}), seed {args.seed}, "
        f"torch {torch.__version__}; train: median of {args.steps} Adam steps of {args.batch} rays "
        f"({split}, autocast {args.autocast}: the steps and the matmul row) after 1 warm-up, every row "
        f"timed in turn; render: {args.render_rays} rays in chunks of {args.chunk}, fp32, 1 timed pass "
        "after 1 warm-up"
    )


def bench_micro_batch(args: argparse.Namespace, profile: str, device: torch.device) -> int | None:
    """`--micro-batch` (0: the whole batch), else what training uses on `device`
    (`task.train.micro_batch_rays`, on CPU `cpu_micro_batch_rays`, of `task=nerf profile=<profile>`)."""
    if args.micro_batch is not None:
        return args.micro_batch or None
    return micro_batch_rays(load_task_config("nerf", profile)["train"], device)


def bench_render_chunk(args: argparse.Namespace, profile: str, device: torch.device) -> int:
    """`--chunk`, else what evaluation uses on `device` (`task.eval.chunk`, on CPU `cpu_chunk`)."""
    if args.chunk is not None:
        return args.chunk
    return render_chunk(load_task_config("nerf", profile)["eval"], device)


def run_nerf(args: argparse.Namespace) -> str:
    """All measurements of `nerf`; returns the printed report (progress goes to stderr).

    The training steps of every model, nerf-pytorch's (`--peer-nerf-pytorch`) and the matmul reference
    are timed round-robin (one step of each in turn, `--steps` times), so that a load change on a shared
    machine affects them alike; then each model renders."""
    if args.threads:
        torch.set_num_threads(args.threads)
    device = pick_device(args.device)
    configs = nerf_model_configs(args.models, args.profile)
    micro = bench_micro_batch(args, args.profile, device)
    args.chunk = bench_render_chunk(args, args.profile, device)
    dataset = load_dataset_config("nerf", args.profile)
    camera = BenchCamera.from_dataset(dataset)
    peer_module = load_nerf_pytorch(args.peer_nerf_pytorch) if args.peer_nerf_pytorch else None
    seed_everything(args.seed)
    generator = torch.Generator().manual_seed(args.seed)
    train_rays = benchmark_rays(args.batch, generator, device, shuffle=True, camera=camera)
    target = torch.rand(args.batch, 3, generator=generator).to(device)
    render_rays = benchmark_rays(args.render_rays, generator, device, shuffle=False, camera=camera)
    amp_dtype = NERF_AUTOCAST_DTYPES[args.autocast]
    models, steps = {}, []
    for name, cfg in configs.items():
        torch.manual_seed(args.seed)
        models[name] = build_method(cfg).to(device)
        steps.append(train_step_fn(models[name], train_rays, target, micro, amp_dtype))
    first = next(iter(models.values()))
    rows_per_step = args.batch * sum(first.samples_per_level())
    matmul_dtype = amp_dtype or torch.float32
    matmul, matmul_flops = matmul_reference(rows_per_step, MATMUL_WIDTH, device, matmul_dtype)
    peer = None
    if peer_module is not None:
        peer = NerfPytorchStep(peer_module, camera.near, camera.far, args.seed)
        steps.append(peer.step_fn(train_rays, target))
    print(
        f"training steps: {', '.join(models)}{', nerf-pytorch' if peer else ''} and a matmul, "
        f"{args.steps} rounds after 1 warm-up ...",
        file=sys.stderr,
        flush=True,
    )
    seconds = time_calls([*steps, matmul], device, args.steps, warmup=1)
    rows = [
        model_row(name, model, t, args.batch)
        for (name, model), t in zip(models.items(), seconds, strict=False)
    ]
    for i, (name, model) in enumerate(models.items(), start=1):
        print(f"[{i}/{len(models)}] {name}: rendering ...", file=sys.stderr, flush=True)
        rows[i - 1].render_seconds = time_rendering(model, render_rays, args.chunk, device)
        rows[i - 1].render_rays = args.render_rays
    if peer is not None:
        note = "github.com/yenchenlin/nerf-pytorch, lego settings (64+192 samples)"
        rows.append(
            NerfRow(
                "nerf-pytorch",
                peer.parameters(),
                peer.flops_per_ray(),
                seconds[-2],
                args.batch,
                note=note,
                kind="peer",
            )
        )
    name = f"matmul [{rows_per_step},{MATMUL_WIDTH}]x[{MATMUL_WIDTH},{MATMUL_WIDTH}]"
    name += "" if amp_dtype is None else " bf16"
    reference = NerfRow(
        name,
        None,
        matmul_flops // (3 * args.batch),
        seconds[-1],
        args.batch,
        note="fwd + 2 bwd matmuls, reference",
        kind="reference",
    )
    rows.append(reference)
    return "\n".join(
        [
            _nerf_header(args, device, micro),
            format_nerf_table(rows),
            "",
            *nerf_ratio_lines(rows),
            *nerf_footnotes(rows[0].name, reference),
        ]
    )
