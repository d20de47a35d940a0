"""Timing one radiance field: training steps and rendering on the rays of one benchmark camera."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch

from src.bench.timing import time_runs
from src.data.rays import focal_from_fov, generate_rays
from src.models.instantiate import build_method
from src.models.nerf.inference import render_rays_chunked
from src.models.nerf.models import NerfModelBase, RefNeRF
from src.models.nerf.summary import nerf_mlp_flops_per_ray
from src.models.parameters import count_parameters
from src.render.multiview_cameras import look_at_c2w, sphere_position


@dataclass(frozen=True)
class BenchCamera:
    """The camera of the `nerf` benchmark rays: at ``radius`` from the origin, looking at it, at the first
    pose of the NeRF dataset's test circle, with the dataset's field of view and ray interval."""

    radius: float
    elevation_deg: float
    azimuth_deg: float
    camera_angle_x: float  # horizontal field of view, radians
    near: float
    far: float

    @classmethod
    def from_dataset(cls, ds: Mapping[str, Any]) -> BenchCamera:
        """From a NeRF dataset config (conf/dataset/nerf_procedural.yaml: ``radius``, ``test_elevation_deg``,
        ``test_azimuth_start_deg``, ``camera_angle_x``, ``near``, ``far``)."""
        return cls(
            float(ds["radius"]),
            float(ds["test_elevation_deg"]),
            float(ds["test_azimuth_start_deg"]),
            float(ds["camera_angle_x"]),
            float(ds["near"]),
            float(ds["far"]),
        )


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


def benchmark_rays(
    n: int, generator: torch.Generator, device: torch.device, shuffle: bool, camera: BenchCamera
) -> dict[str, torch.Tensor]:
    """`n` rays (`RAY_KEYS`) of `camera` (by default radius 4 looking at the origin, near 2, far 6):
    the pixels of a square image just large enough, in image order or (`shuffle`) a random subset."""
    side = max(2, math.isqrt(n - 1) + 1)  # side * side >= n
    position = sphere_position(
        camera.radius, math.radians(camera.elevation_deg), math.radians(camera.azimuth_deg)
    )
    c2w = look_at_c2w(position)
    focal = focal_from_fov(camera.camera_angle_x, side)
    rays = generate_rays(c2w, focal, side, side, camera.near, camera.far)
    pick = torch.randperm(side * side, generator=generator)[:n] if shuffle else torch.arange(n)
    return {key: value[pick].to(device) for key, value in rays.items()}


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
