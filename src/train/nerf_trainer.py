"""Training loop for the radiance fields (`task=nerf`, `stage=train`).

One job fits one scene (`task.scene`) of the dataset: random batches of training rays (`RayBatcher`,
whose batch at step s depends only on (seed, s)), Adam with the log-linear schedule and warm-up of
mip-NeRF (`task.train.lr_*`), optional gradient clipping, and NeRF's centre-crop warm-up for the first
`precrop_iters` steps. Per `log_every` steps the loss components (`train_loss_<component>`) and the fine
level's PSNR are logged; per `val_every` steps the same on a fixed subset of validation rays
(`val_loss_*`, `val_psnr`), also written to `curves.csv`.

Resume: the checkpoint holds the step, the model, the optimiser, the torch RNG (stratified sampling
draws from it) and the curves, so an interrupted and resumed run ends with the same weights.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from src.data.blender import load_blender_split
from src.data.ray_batches import RayBatcher
from src.data.rays import rays_for_pixels
from src.models.denoise.summary import count_parameters
from src.models.instantiate import build_method
from src.train.checkpoint import (
    FINAL_NAME,
    LAST_NAME,
    restore_training_state,
    save_checkpoint,
    training_state,
)
from src.train.curves import write_curves
from src.train.device import pick_device, seed_everything
from src.train.schedules import log_linear_lr

log = logging.getLogger(__name__)


def scene_dir(cfg: DictConfig) -> Path:
    """The folder of the scene this job fits: `<paths.scenes>/<task.scene>`."""
    return Path(cfg.paths.scenes) / str(cfg.task.scene)


def load_split(cfg: DictConfig, split: str, max_images: int | None = None):
    """A Blender-format split of this job's scene, composited on `dataset.background`."""
    return load_blender_split(
        scene_dir(cfg),
        split,
        background=tuple(cfg.dataset.background),
        downscale=int(cfg.dataset.get("downscale", 1) or 1),
        max_images=max_images,
    )


def mse_to_psnr(mse: float) -> float:
    """PSNR in dB of a mean squared error on [0, 1] images."""
    return -10.0 * math.log10(max(mse, 1e-12))


def split_metrics(split: str, values: dict[str, float]) -> dict[str, float]:
    """`{split}_psnr` and `{split}_loss_<component>` metric names for a step's or validation's values."""
    metrics = {f"{split}_psnr": values["psnr"]}
    return metrics | {f"{split}_loss_{k}": v for k, v in values.items() if k != "psnr"}


def _model_config(cfg: DictConfig) -> dict[str, Any]:
    return OmegaConf.to_container(cfg.model, resolve=True)


class NerfTrainer:
    """Owns the model, optimiser, ray batches and step of one training run."""

    def __init__(self, cfg: DictConfig, tracker, on_step: Callable[[int], None] | None = None) -> None:
        t = cfg.task.train
        self.cfg, self.t, self.tracker, self.on_step = cfg, t, tracker, on_step
        self.device = pick_device(cfg.device)
        seed_everything(int(cfg.seed))
        self.model_cfg = _model_config(cfg)
        self.model = build_method(self.model_cfg).to(self.device)
        self.optimizer = torch.optim.Adam(
            self.model.parameters(),
            lr=float(t.lr_init),
            betas=(float(t.adam_beta1), float(t.adam_beta2)),
            eps=float(t.adam_eps),
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
            device=self.device,
        )
        self.val_rays = self._validation_rays(near, far)
        self.step = 0
        self.train_seconds = 0.0
        self.curves: list[dict[str, float]] = []
        self.checkpoint_dir = Path(t.checkpoint_dir)

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

    # -- checkpoints ---------------------------------------------------------------------------------
    def state(self) -> dict[str, Any]:
        # One position counter: the step (a NeRF run has no epochs over a fixed batch order).
        return training_state(self, 0, self.step, self.step, task="nerf")

    def save(self, name: str = LAST_NAME) -> Path:
        path = self.checkpoint_dir / name
        save_checkpoint(path, self.state())
        return path

    def restore(self, path: str) -> None:
        self.step = int(restore_training_state(self, path)["step"])
        log.info("resumed from %s at step %d", path, self.step)

    # -- loop ----------------------------------------------------------------------------------------
    def learning_rate(self, step: int) -> float:
        t = self.t
        decay = (float(t.lr_init), float(t.lr_final), int(t.max_steps))
        return log_linear_lr(step, *decay, int(t.lr_delay_steps), float(t.lr_delay_mult))

    def train_step(self) -> dict[str, float]:
        self.model.train()
        for group in self.optimizer.param_groups:
            group["lr"] = self.learning_rate(self.step)
        batch = self.batcher.batch(self.step)
        outputs = self.model(batch, randomized=True)
        loss, components = self.model.loss(outputs, batch["rgb"])
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if self.t.grad_max_norm:
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), float(self.t.grad_max_norm))
        self.optimizer.step()
        fine_mse = float(torch.mean((outputs[-1]["rgb"].detach() - batch["rgb"]) ** 2))
        return {"loss": float(loss.detach()), "psnr": mse_to_psnr(fine_mse), **components}

    @torch.no_grad()
    def validate(self) -> dict[str, float]:
        """Loss components and fine-level PSNR on the fixed validation rays, `chunk` rays at a time
        (Ref-NeRF differentiates its density for the normals inside the model even here)."""
        self.model.eval()
        rays, chunk, n = self.val_rays, int(self.t.chunk), len(self.val_rays["rgb"])
        totals: dict[str, float] = {}
        squared = 0.0
        for start in range(0, n, chunk):
            part = {k: v[start : start + chunk] for k, v in rays.items()}
            outputs = self.model(part, randomized=False)
            loss, components = self.model.loss(outputs, part["rgb"])
            size = len(part["rgb"])
            for k, v in {"loss": float(loss.detach()), **components}.items():
                totals[k] = totals.get(k, 0.0) + v * size
            squared += float(torch.sum((outputs[-1]["rgb"].detach() - part["rgb"]) ** 2)) / 3
        means = {k: v / n for k, v in totals.items()}
        return {**means, "psnr": mse_to_psnr(squared / n)}

    def _log(self, metrics: dict[str, float]) -> dict[str, float]:
        self.tracker.log_metrics(metrics, step=self.step)
        return metrics

    def fit(self) -> dict[str, Any]:
        """Train until `max_steps`; checkpoint every `checkpoint_every` steps, on Ctrl-C and at the end."""
        t = self.t
        max_steps = int(t.max_steps)
        bar = tqdm(total=max_steps, initial=self.step, desc=f"train {self.model_cfg['name']}", unit="step")
        if self.step == 0:  # the curves start at the initialisation
            self.curves.append({"step": 0, **self._log(split_metrics("val", self.validate()))})
        try:
            while self.step < max_steps:
                start = time.perf_counter()
                values = self.train_step()
                self.train_seconds += time.perf_counter() - start
                self.step += 1
                bar.update(1)
                bar.set_postfix(loss=f"{values['loss']:.4f}", psnr=f"{values['psnr']:.2f}")
                train_metrics = split_metrics("train", values)
                if self.step % int(t.log_every) == 0:
                    self._log(train_metrics)
                if self.step % int(t.val_every) == 0 or self.step == max_steps:
                    row = self._log(split_metrics("val", self.validate())) | train_metrics
                    self.curves.append({"step": self.step, **row})
                    write_curves(t.curves_file, self.curves)
                if self.step % int(t.checkpoint_every) == 0:
                    self.save()
                if self.on_step is not None:
                    self.on_step(self.step)
        except KeyboardInterrupt:
            self.save()  # resume continues from exactly here
            raise
        finally:
            bar.close()
        final = self.save(FINAL_NAME)
        return {
            "checkpoint": str(final),
            "steps": self.step,
            "train_time_s": self.train_seconds,
            "param_count": count_parameters(self.model),
            "train_rays_per_s": self.step * int(t.batch_size) / max(self.train_seconds, 1e-9),
            **(self.curves[-1] if self.curves else {}),
        }


def train_nerf(cfg: DictConfig, tracker, on_step: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Fit `cfg.model` to scene `task.scene`; resume from `task.train.resume` when set."""
    trainer = NerfTrainer(cfg, tracker, on_step)
    if cfg.task.train.resume:
        trainer.restore(cfg.task.train.resume)
    summary = trainer.fit()
    keys = ("train_time_s", "param_count", "steps", "train_rays_per_s")
    tracker.log_metrics({k: summary[k] for k in keys}, step=summary["steps"])
    return summary
