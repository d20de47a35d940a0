"""Evaluation of a trained radiance field on the test views (`task=nerf`, `stage=eval`).

Every test view of `task.scene` is rendered through pixel centres, `task.eval.chunk` rays at a time
(memory bounded at any resolution), timed after one warm-up view, and scored against the view composited
on the dataset background: PSNR, SSIM, LPIPS (and the other `metrics:` scores) with the conventions of
`src.metrics.image`; the NeRF task's `metrics.tonemap` is `clip` since the images are already sRGB.

Writes `metrics.json` (means), `per_image.csv`, `provenance.json`, and PNGs of the rendered view, the
reference, depth (near = white, far = black over the accumulated opacity) and, for Ref-NeRF, normals.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from src.data.blender import load_split, scene_dir
from src.data.rays import generate_rays
from src.eval.loop import Evaluation
from src.io.images import write_png
from src.metrics.image import image_metrics
from src.models.nerf.inference import render_rays_chunked
from src.models.nerf.models import NerfModelBase
from src.models.nerf.summary import nerf_mlp_flops_per_ray
from src.train.nerf_trainer import render_chunk


def render_view(model: NerfModelBase, c2w: np.ndarray, split, cfg: DictConfig) -> dict[str, np.ndarray]:
    """One full view: {rgb (H, W, 3), depth (H, W), acc (H, W)[, normals (H, W, 3)]} as numpy."""
    rays = generate_rays(
        torch.from_numpy(c2w), split.focal, split.width, split.height, cfg.dataset.near, cfg.dataset.far
    )
    out = render_rays_chunked(model, rays, render_chunk(cfg.task.eval, next(model.parameters()).device))
    shape = (split.height, split.width)
    return {k: v.reshape(*shape, -1).squeeze(-1).numpy() for k, v in out.items()}


def quantize_8bit(image: np.ndarray) -> np.ndarray:
    """An image in [0, 1] as it is stored in an 8-bit PNG: round(255 x) / 255. NeRF papers score the
    images they save (multinerf's `eval_quantize_metrics`, NerfBaselines, the NeRF seed thesis), so PSNR
    is comparable only on quantised images (unquantised it is ~0.1-0.3 dB higher at high quality)."""
    return np.round(np.clip(image, 0.0, 1.0) * 255.0) / 255.0


def depth_image(depth: np.ndarray, acc: np.ndarray, near: float, far: float) -> np.ndarray:
    """Depth as grey levels: near white, far black, faded to white (the background) by 1 - acc."""
    grey = 1.0 - np.clip((depth - near) / (far - near), 0.0, 1.0)
    grey = grey * acc + (1.0 - acc)
    return np.repeat(grey[..., None], 3, axis=-1)


class NerfEvaluation(Evaluation):
    """Every view of `task.eval.split` of the scene, rendered through pixel centres."""

    unit = "view"
    artifact_folders = ("png", "buffers")

    def __init__(self, cfg: DictConfig, tracker) -> None:
        super().__init__(cfg, tracker)
        self.split = load_split(cfg, str(cfg.task.eval.split), cfg.task.eval.max_images)
        # the cost card: MLP forward FLOPs per ray at the model's nominal samples per level (samples an
        # occupancy grid skips are counted: with one, the achieved GFLOP/s is an upper bound)
        self.flops_per_ray = float(nerf_mlp_flops_per_ray(self.model)["total"])

    def items(self) -> Sequence[int]:
        return range(len(self.split.names))

    def infer(self, i: int) -> dict[str, np.ndarray]:
        return render_view(self.model, self.split.c2w[i : i + 1], self.split, self.cfg)

    def data_dir(self) -> Path:
        return scene_dir(self.cfg)

    def header(self) -> dict[str, Any]:
        return {
            "model": self.cfg.model.name,
            "scene": self.cfg.task.scene,
            "flops_per_ray": self.flops_per_ray,
        }

    def logged_metrics(self, summary: dict[str, Any]) -> dict[str, float]:
        return super().logged_metrics(summary) | {"eval_flops_per_ray": self.flops_per_ray}

    def _name(self, i: int) -> str:
        return f"{self.cfg.task.scene}-{Path(self.split.names[i]).name}"

    def score(self, i: int, rendered: dict[str, np.ndarray], seconds: float) -> dict[str, Any]:
        megapixels = self.split.width * self.split.height / 1e6
        row: dict[str, Any] = {"view": self._name(i)}
        rendered_rgb, reference = np.clip(rendered["rgb"], 0, 1), self.split.images[i]
        if self.cfg.task.eval.quantize_metrics:
            rendered_rgb, reference = quantize_8bit(rendered_rgb), quantize_8bit(reference)
        row |= image_metrics(rendered_rgb.astype(np.float32), reference.astype(np.float32), self.cfg.metrics)
        row |= {"ms_per_image": seconds * 1e3, "ms_per_mpixel": seconds * 1e3 / megapixels}
        row["rays_per_s"] = megapixels * 1e6 / seconds
        row["gflops"] = self.flops_per_ray * row["rays_per_s"] / 1e9
        return row

    def save_outputs(self, i: int, rendered: dict[str, np.ndarray]) -> None:
        """PNGs of the rendered view and the reference; depth and (Ref-NeRF) normals under buffers/."""
        if not self.cfg.task.eval.save_images:
            return
        name, png, extra = self._name(i), self.out_dir / "png", self.out_dir / "buffers"
        write_png(png / f"{name}-rendered.png", np.clip(rendered["rgb"], 0, 1))
        write_png(png / f"{name}-reference.png", self.split.images[i])
        near, far = float(self.cfg.dataset.near), float(self.cfg.dataset.far)
        write_png(extra / f"{name}-depth.png", depth_image(rendered["depth"], rendered["acc"], near, far))
        if "normals" in rendered:
            write_png(extra / f"{name}-normals.png", np.clip(0.5 * (rendered["normals"] + 1.0), 0, 1))


def evaluate_nerf(cfg: DictConfig, tracker) -> dict[str, Any]:
    """Render and score every test view of the scene; returns (and writes) the summary of means."""
    return NerfEvaluation(cfg, tracker).run(desc=f"eval {cfg.model.name} {cfg.task.scene}")
