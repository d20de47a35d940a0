"""Timing one radiance field: training steps and rendering on the rays of one benchmark camera."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch

from src.bench.timing import time_runs
from src.data.rays import focal_from_fov, generate_rays
from src.models.nerf.inference import render_rays_chunked
from src.models.nerf.models import NerfModelBase, RefNeRF
from src.models.nerf.summary import nerf_mlp_flops_per_ray
from src.models.parameters import count_parameters
from src.render.multiview_cameras import look_at_c2w, sphere_position
from src.train.nerf_trainer import optimizer_step


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
    """One row of the table: a model (`kind` "model"), nerf-pytorch ("peer", no rendering) or the matmul
    reference ("reference": its forward FLOPs spread over the batch's rays, so that the GFLOP/s columns
    compare; no rays/s)."""

    name: str
    params: int | None
    flops_per_ray: int  # MLP forward FLOPs per ray, coarse + fine
    train_seconds: float  # median seconds of one step of `train_rays` rays
    train_rays: int
    render_seconds: float | None = None  # seconds of one pass over `render_rays` rays
    render_rays: int = 0
    note: str = ""
    kind: str = "model"

    @property
    def train_seconds_per_ray(self) -> float:
        return self.train_seconds / self.train_rays

    @property
    def render_seconds_per_ray(self) -> float | None:
        return None if self.render_seconds is None else self.render_seconds / self.render_rays


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
    model: NerfModelBase,
    rays: Mapping[str, torch.Tensor],
    target: torch.Tensor,
    micro_batch_rays: int | None,
    amp_dtype: torch.dtype | None = None,
    lr: float = 5e-4,
) -> Callable[[], None]:
    """One training step on a fixed ray batch, as `NerfTrainer.train_step` does it (`optimizer_step`):
    the batch's stratified and resampling jitter drawn up front, forward + loss + backward in
    micro-batches of `micro_batch_rays` rays (None: the whole batch), under autocast to `amp_dtype`
    (None: fp32), one Adam step."""
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=lr)
    batch = {**rays, "rgb": target}
    return lambda: optimizer_step(model, optimizer, batch, micro_batch_rays, None, amp_dtype)


def time_rendering(
    model: NerfModelBase, rays: Mapping[str, torch.Tensor], chunk: int, device: torch.device
) -> float:
    """Seconds of one `render_rays_chunked` pass over `rays` (after one untimed warm-up pass)."""
    model.eval()
    return time_runs(lambda: render_rays_chunked(model, rays, chunk), device, 1)


def model_note(model: NerfModelBase) -> str:
    coarse, fine = model.samples_per_level()
    note = f"{coarse}+{fine} samples"
    if isinstance(model, RefNeRF):
        gradient = "FLOPs exclude the normals' density gradient"
        note += f"; {gradient if model.density_normals else 'no density-gradient normals'}"
    return note


def model_row(name: str, model: NerfModelBase, train_seconds: float, n_train: int) -> NerfRow:
    flops = nerf_mlp_flops_per_ray(model)["total"]
    note = model_note(model)
    return NerfRow(name, count_parameters(model), flops, train_seconds, n_train, note=note)


def matmul_reference(
    rows: int, width: int, device: torch.device, dtype: torch.dtype = torch.float32
) -> tuple[Callable[[], None], int]:
    """The machine's achievable matmul throughput, measured like a training step of a `width`-wide linear
    layer over `rows` samples: y = x W^T, then g W and g^T x (its input and weight gradients), in `dtype`
    (fp32, or bf16 to compare a bf16-autocast step with). Returns (the function, its FLOPs:
    3 x 2 x rows x width^2)."""
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(rows, width, generator=gen).to(device, dtype)
    g = torch.randn(rows, width, generator=gen).to(device, dtype)
    w = (torch.randn(width, width, generator=gen) / width**0.5).to(device, dtype)
    bias = torch.zeros(width, device=device, dtype=dtype)
    y, gx = torch.empty_like(x), torch.empty_like(x)
    gw = torch.empty_like(w)

    def run() -> None:
        torch.addmm(bias, x, w.t(), out=y)
        torch.mm(g, w, out=gx)
        torch.mm(g.t(), x, out=gw)

    return run, 3 * 2 * rows * width * width
