"""Training loop for the radiance fields (`task=nerf`, `stage=train`).

One job fits one scene (`task.scene`) of the dataset: random batches of training rays (`RayBatcher`,
whose batch at step s depends only on (seed, s)), Adam with the log-linear schedule and warm-up of
mip-NeRF (`task.train.lr_*`), optional gradient clipping, and NeRF's centre-crop warm-up for the first
`precrop_iters` steps. Per `log_every` steps the loss components (`train_loss_<component>`) and the fine
level's PSNR are logged; per `val_every` steps the same on a fixed subset of validation rays
(`val_loss_*`, `val_psnr`), also written to `curves.csv`.

The loop itself (progress, checkpoints, resume, Ctrl-C) is the shared `src.train.loop.TrainingLoop`: a
NeRF run is one epoch of `max_steps` batches. The checkpoint holds the step, the model, the optimiser, the
RNG states (stratified sampling draws from them, on the training device) and the curves, so a resumed run
ends with the same weights.

A model with an occupancy grid (`model.occupancy_grid`, empty-space skipping) has it updated at the start
of every step from the model's own density (`OccupancyGrid.update`, which acts every `update_every`
steps), with jitter from a generator seeded by (seed, step): the grid is model state (buffers) and so
checkpointed, and a resumed run updates it exactly as an uninterrupted one.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Iterator, Mapping
from typing import Any

import torch
from omegaconf import DictConfig
from tqdm import tqdm

from src.data.blender import load_split
from src.data.ray_batches import RayBatcher, step_seed
from src.data.rays import rays_for_pixels
from src.errors import ConfigError
from src.models.nerf.summary import activation_bytes, activation_bytes_per_ray, fitting_micro_batch
from src.train.curves import write_curves
from src.train.device import autocast, autocast_dtype
from src.train.loop import Means, OnStep, TrainingLoop, run_training

log = logging.getLogger(__name__)


def mse_to_psnr(mse: float) -> float:
    """PSNR in dB of a mean squared error on [0, 1] images."""
    return -10.0 * math.log10(max(mse, 1e-12))


def split_metrics(split: str, values: dict[str, float]) -> dict[str, float]:
    """`{split}_psnr` and `{split}_loss_<component>` metric names for a step's or validation's values."""
    metrics = {f"{split}_psnr": values["psnr"]}
    return metrics | {f"{split}_loss_{k}": v for k, v in values.items() if k != "psnr"}


def device_free_bytes(device: torch.device) -> int | None:
    """Free memory of a CUDA training device (`torch.cuda.mem_get_info`); None elsewhere (no check)."""
    if device.type != "cuda":
        return None
    return int(torch.cuda.mem_get_info(device)[0])


def check_activation_memory(
    model, batch_size: int, micro_batch_rays: int | None, free_bytes: int | None
) -> None:
    """Stop before training, with one line naming `task.train.micro_batch_rays` and a value that fits,
    when the step's estimated activations (`summary.activation_bytes`) exceed the device's `free_bytes`
    (None: not a CUDA device, nothing to check)."""
    if free_bytes is None:
        return
    rays = batch_size if micro_batch_rays is None else min(int(micro_batch_rays), batch_size)
    need = activation_bytes(model, rays)
    if need <= free_bytes:
        return
    fit = fitting_micro_batch(model, free_bytes)
    advice = (
        f"set task.train.micro_batch_rays={fit} (or less)"
        if fit
        else "not even one ray fits; free GPU memory or use fewer samples"
    )
    raise ConfigError(
        f"task.train.micro_batch_rays={micro_batch_rays}: a training step of {rays} rays needs about "
        f"{need / 1e9:.1f} GB of activations ({activation_bytes_per_ray(model) / 1e3:.0f} KB per ray) "
        f"but the GPU has {free_bytes / 1e9:.1f} GB free; {advice}"
    )


def micro_batch_rays(train_cfg: Mapping[str, Any], device: torch.device) -> int | None:
    """Rays per forward + backward pass of a training step: `task.train.micro_batch_rays` when set, else
    on CPU `task.train.cpu_micro_batch_rays` (a few rays' activations fit in the caches, where the
    elementwise passes run at cache instead of memory speed; the step is the same, `accumulate_gradients`),
    else None (the whole batch at once)."""
    micro = train_cfg.get("micro_batch_rays")
    if micro is None and device.type == "cpu":
        micro = train_cfg.get("cpu_micro_batch_rays")
    return None if micro is None else int(micro)


def render_chunk(section: Mapping[str, Any], device: torch.device) -> int:
    """Rays per forward pass when rendering (`task.eval`) or validating (`task.train`): the section's
    `cpu_chunk` on a CPU when set, else its `chunk`. On a CPU a few rays' activations stay in cache: at
    paper size 64-ray chunks rendered at the training step's GFLOP/s, 4096-ray ones at ~55 % of it."""
    chunk = section.get("cpu_chunk") if device.type == "cpu" else None
    return int(section["chunk"] if chunk is None else chunk)


def accumulate_gradients(
    model,
    batch: dict[str, torch.Tensor],
    micro_batch_rays: int | None,
    noise: dict[str, torch.Tensor],
    amp_dtype: torch.dtype | None = None,
) -> dict[str, float]:
    """Backpropagate the loss of `batch` in micro-batches of `micro_batch_rays` rays (None: one pass),
    adding to the parameters' `.grad`; returns the logged values of the whole batch (loss, components,
    fine-level PSNR).

    Every loss term is a mean over rays (the per-level MSEs, and Ref-NeRF's regularisers, each a per-ray
    sum over samples averaged over rays; `coarse_loss_mult` and the regularisers' multipliers are
    constant weights of such means), so the loss of the batch is sum_k (n_k / N) loss_k over micro-batches
    of n_k rays: backpropagating each micro-batch's loss times its share of the rays accumulates exactly
    the gradient of the unsplit batch (up to float summation order). The stratified and resampling jitter
    is drawn for the whole batch up front (`noise`, `draw_noise`) and sliced, so every ray is sampled as
    in the unsplit step. Activation memory then scales with `micro_batch_rays` instead of the batch size.
    `amp_dtype` (bfloat16) runs forward and loss under autocast (the MLPs' matmuls in it, compositing in
    fp32: `NerfModelBase.forward`); the backward pass follows the forward's dtypes.
    """
    n = len(batch["rgb"])
    size = n if micro_batch_rays is None else max(1, min(int(micro_batch_rays), n))
    totals: dict[str, float] = {}
    squared = 0.0
    for start in range(0, n, size):
        part = {k: v[start : start + size] for k, v in batch.items()}
        part_noise = {k: v[start : start + size] for k, v in noise.items()}
        share = len(part["rgb"]) / n
        with autocast(part["rgb"].device.type, amp_dtype):
            outputs = model(part, randomized=True, noise=part_noise)
            loss, components = model.loss(outputs, part["rgb"])
        (loss * share).backward()
        for key, value in {"loss": float(loss.detach()), **components}.items():
            totals[key] = totals.get(key, 0.0) + share * float(value)
        squared += float(torch.sum((outputs[-1]["rgb"].detach() - part["rgb"]) ** 2))
        del outputs, loss  # free this micro-batch's graph before the next one's forward
    return {**totals, "psnr": mse_to_psnr(squared / (3 * n))}


def optimizer_step(
    model,
    optimizer,
    batch: dict[str, torch.Tensor],
    micro_batch_rays: int | None,
    grad_max_norm,
    amp_dtype: torch.dtype | None = None,
) -> dict[str, float]:
    """One optimiser step on `batch`: the whole batch's stratified jitter drawn up front (from the global
    RNG of the training device, as an unsplit forward draws it), gradients accumulated over micro-batches
    (`accumulate_gradients`), then gradient clipping at `grad_max_norm` (None/0: off) and the optimiser
    step, once. The same step whatever `micro_batch_rays` is; `amp_dtype`: autocast (None: fp32)."""
    model.train()
    noise = model.draw_noise(len(batch["rgb"]), batch["near"])
    optimizer.zero_grad(set_to_none=True)
    values = accumulate_gradients(model, batch, micro_batch_rays, noise, amp_dtype)
    if grad_max_norm:
        torch.nn.utils.clip_grad_norm_(model.parameters(), float(grad_max_norm))
    optimizer.step()
    return values


#: `step_seed` stream of the occupancy grid's jitter (stream 0: the ray batches).
OCCUPANCY_STREAM = 1


def update_occupancy(model, seed: int, step: int) -> bool:
    """Update the model's occupancy grid, if it has one, before step `step` (0-based) from the model's
    point density; its jitter depends only on (seed, step). Returns whether the grid changed."""
    grid = getattr(model, "occupancy_grid", None)
    if grid is None:
        return False
    generator = torch.Generator(device="cpu").manual_seed(step_seed(seed, step, OCCUPANCY_STREAM))
    return grid.update(model.point_density, step, generator)


class NerfTrainer(TrainingLoop):
    """Random ray batches of one scene, validation every `val_every` steps."""

    lr_key = "lr_init"

    def __init__(self, cfg: DictConfig, tracker, on_step: OnStep = None) -> None:
        super().__init__(cfg, tracker, on_step)
        t = self.t
        check_activation_memory(
            self.model, int(t.batch_size), t.get("micro_batch_rays"), device_free_bytes(self.device)
        )
        near, far = float(cfg.dataset.near), float(cfg.dataset.far)
        train = load_split(cfg, "train", t.max_train_images)
        self.batcher = RayBatcher.from_split(
            train,
            near=near,
            far=far,
            batch_size=int(t.batch_size),
            seed=int(cfg.seed),
            precrop_iters=int(t.precrop_iters),
            precrop_frac=float(t.precrop_frac),
            batching=str(t.get("batching", "all_images")),
            device=self.device,
        )
        self.val_rays = self._validation_rays(near, far)

    def _validation_rays(self, near: float, far: float) -> dict[str, torch.Tensor]:
        """A fixed random subset (`val_rays`) of the validation views' rays, the same every time."""
        val = load_split(self.cfg, "val", self.t.max_val_images)
        images = torch.from_numpy(val.images)
        c2w = torch.from_numpy(val.c2w)
        gen = torch.Generator().manual_seed(int(self.cfg.seed))
        n = int(self.t.val_rays)
        cam = torch.randint(0, images.shape[0], (n,), generator=gen)
        row = torch.randint(0, val.height, (n,), generator=gen)
        col = torch.randint(0, val.width, (n,), generator=gen)
        rays = rays_for_pixels(c2w, cam, row, col, val.focal, val.width, val.height, near, far)
        rays["rgb"] = images[cam, row, col]
        return {k: v.to(self.device) for k, v in rays.items()}

    def checkpoint_extra(self) -> dict[str, Any]:
        return {"task": "nerf"}

    # -- the task's part of the loop ----------------------------------------------------------------------
    def batches(self, epoch: int, skip: int = 0) -> Iterator[dict[str, torch.Tensor]]:
        """The batch of step s depends only on (seed, s): one epoch of `max_steps` batches."""
        return (self.batcher.batch(step) for step in range(skip, int(self.t.max_steps)))

    def done(self) -> bool:
        return self.pos.step >= int(self.t.max_steps)

    def train_step(self, batch: dict[str, torch.Tensor]) -> tuple[dict[str, float], int]:
        update_occupancy(self.model, int(self.cfg.seed), self.pos.step)
        micro = micro_batch_rays(self.t, self.device)
        amp_dtype = autocast_dtype(bool(self.t.get("amp", False)), self.device)
        values = optimizer_step(self.model, self.optimizer, batch, micro, self.t.grad_max_norm, amp_dtype)
        return values, len(batch["rgb"])

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Loss components and fine-level PSNR on the fixed validation rays, `chunk` rays at a time
        (Ref-NeRF differentiates its density for the normals inside the model even here)."""
        self.model.eval()
        rays, chunk, n = self.val_rays, render_chunk(self.t, self.device), len(self.val_rays["rgb"])
        means = Means()
        squared = 0.0
        for start in range(0, n, chunk):
            part = {k: v[start : start + chunk] for k, v in rays.items()}
            outputs = self.model(part, randomized=False)
            loss, components = self.model.loss(outputs, part["rgb"])
            means.add({"loss": float(loss.detach()), **components}, len(part["rgb"]))
            squared += float(torch.sum((outputs[-1]["rgb"].detach() - part["rgb"]) ** 2)) / 3
        return {**means.result(), "psnr": mse_to_psnr(squared / n)}

    def _log(self, metrics: dict[str, float]) -> dict[str, float]:
        self.tracker.log_metrics(metrics, step=self.pos.step)
        return metrics

    def _validation_point(self) -> dict[str, float]:
        """The validation metrics and the training clock at this step (`train_time_s`: ray batches and
        optimiser steps, not validation), logged: a point of the quality-against-time curves."""
        return self._log(split_metrics("val", self.validate()) | {"train_time_s": self.train_seconds})

    def before_training(self) -> None:
        if self.pos.step == 0:  # the curves start at the initialisation
            self.curves.append({"step": 0, **self._validation_point()})

    def after_step(self, values: dict[str, float], size: int, bar: tqdm) -> None:
        """Progress; train metrics every `log_every`, validation every `val_every` and at the end,
        a checkpoint every `checkpoint_every` steps."""
        t, step = self.t, self.pos.step
        bar.update(1)
        bar.set_postfix(loss=f"{values['loss']:.4f}", psnr=f"{values['psnr']:.2f}")
        train_metrics = split_metrics("train", values)
        if step % int(t.log_every) == 0:
            self._log(train_metrics)
        if step % int(t.val_every) == 0 or step == int(t.max_steps):
            row = self._validation_point() | train_metrics
            self.curves.append({"step": step, **row})
            write_curves(t.curves_file, self.curves)
        if step % int(t.checkpoint_every) == 0:
            self.save()

    def extra_summary(self) -> dict[str, Any]:
        rays_per_s = self.pos.step * int(self.t.batch_size) / max(self.train_seconds, 1e-9)
        return {"train_rays_per_s": rays_per_s, **(self.curves[-1] if self.curves else {})}


def train_nerf(cfg: DictConfig, tracker, on_step: OnStep = None) -> dict[str, Any]:
    """Fit `cfg.model` to scene `task.scene`; resume from `task.train.resume` when set."""
    logged = ("train_time_s", "param_count", "steps", "train_rays_per_s")
    return run_training(NerfTrainer, cfg, tracker, on_step, logged)
