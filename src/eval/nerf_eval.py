"""Evaluation of a trained radiance field on the test views (`task=nerf`, `stage=eval`).

Every test view of `task.scene` is rendered through pixel centres, `task.eval.chunk` rays at a time
(memory bounded at any resolution), timed after one warm-up view, and scored against the view composited
on the dataset background: PSNR, SSIM, LPIPS (and the other `metrics:` scores) with the conventions of
`src.metrics.image`; the NeRF task's `metrics.tonemap` is `clip` since the images are already sRGB.

Writes `metrics.json` (means), `per_image.csv`, `provenance.json`, and PNGs of the rendered view, the
reference, depth (near = white, far = black over the accumulated opacity) and, for Ref-NeRF, normals.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from src.data.rays import generate_rays
from src.eval.common import mean_rows, sync
from src.io.atomic import atomic_write_csv, atomic_write_json
from src.io.images import write_png
from src.metrics.image import image_metrics, lpips_variant
from src.models.denoise.summary import count_parameters
from src.models.instantiate import build_method
from src.models.nerf.inference import render_rays_chunked
from src.models.nerf.models import NerfModelBase
from src.provenance import provenance
from src.train.checkpoint import load_weights
from src.train.device import pick_device
from src.train.nerf_trainer import load_split, scene_dir


def load_nerf(cfg: DictConfig, device: torch.device) -> NerfModelBase:
    """The model of `task.eval.checkpoint`, checked against `cfg.model`."""
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    model = build_method(model_cfg)
    load_weights(model, model_cfg, str(cfg.task.eval.checkpoint))
    return model.to(device).eval()


def render_view(model: NerfModelBase, c2w: np.ndarray, split, cfg: DictConfig) -> dict[str, np.ndarray]:
    """One full view: {rgb (H, W, 3), depth (H, W), acc (H, W)[, normals (H, W, 3)]} as numpy."""
    rays = generate_rays(
        torch.from_numpy(c2w), split.focal, split.width, split.height, cfg.dataset.near, cfg.dataset.far
    )
    out = render_rays_chunked(model, rays, int(cfg.task.eval.chunk))
    shape = (split.height, split.width)
    return {k: v.reshape(*shape, -1).squeeze(-1).numpy() for k, v in out.items()}


def _timed_render(model, c2w, split, cfg, device) -> tuple[dict[str, np.ndarray], float]:
    sync(device)
    start = time.perf_counter()
    out = render_view(model, c2w, split, cfg)
    sync(device)
    return out, time.perf_counter() - start


def depth_image(depth: np.ndarray, acc: np.ndarray, near: float, far: float) -> np.ndarray:
    """Depth as grey levels: near white, far black, faded to white (the background) by 1 - acc."""
    grey = 1.0 - np.clip((depth - near) / (far - near), 0.0, 1.0)
    grey = grey * acc + (1.0 - acc)
    return np.repeat(grey[..., None], 3, axis=-1)


def _save_pngs(out_dir: Path, name: str, rendered: dict[str, np.ndarray], reference: np.ndarray, cfg) -> None:
    png = out_dir / "png"
    write_png(png / f"{name}-rendered.png", np.clip(rendered["rgb"], 0, 1))
    write_png(png / f"{name}-reference.png", reference)
    extra = out_dir / "buffers"
    near, far = float(cfg.dataset.near), float(cfg.dataset.far)
    write_png(extra / f"{name}-depth.png", depth_image(rendered["depth"], rendered["acc"], near, far))
    if "normals" in rendered:
        write_png(extra / f"{name}-normals.png", np.clip(0.5 * (rendered["normals"] + 1.0), 0, 1))


def evaluate_nerf(cfg: DictConfig, tracker) -> dict[str, Any]:
    """Render and score every test view of the scene; returns (and writes) the summary of means."""
    e = cfg.task.eval
    device = pick_device(cfg.device)
    model = load_nerf(cfg, device)
    split = load_split(cfg, str(e.split), e.max_images)
    out_dir = Path(e.out_dir)
    rows: list[dict[str, Any]] = []
    megapixels = split.width * split.height / 1e6
    for i in tqdm(range(len(split.names)), desc=f"eval {cfg.model.name} {cfg.task.scene}", unit="view"):
        if i == 0:  # warm-up: one-time costs are not part of the render time
            render_view(model, split.c2w[:1], split, cfg)
        rendered, seconds = _timed_render(model, split.c2w[i : i + 1], split, cfg, device)
        name = f"{cfg.task.scene}-{Path(split.names[i]).name}"
        row: dict[str, Any] = {"view": name}
        row |= image_metrics(np.clip(rendered["rgb"], 0, 1), split.images[i], cfg.metrics)
        row |= {"ms_per_image": seconds * 1e3, "ms_per_mpixel": seconds * 1e3 / megapixels}
        row["rays_per_s"] = megapixels * 1e6 / seconds
        rows.append(row)
        if e.save_images:
            _save_pngs(out_dir, name, rendered, split.images[i], cfg)
    summary: dict[str, Any] = {"images": len(rows), "mean": mean_rows(rows)}
    summary["param_count"] = count_parameters(model)
    variant = lpips_variant(cfg.metrics)
    if variant is not None:
        summary["lpips_variant"] = variant
    atomic_write_json(out_dir / "metrics.json", {"model": cfg.model.name, "scene": cfg.task.scene, **summary})
    atomic_write_json(out_dir / "provenance.json", provenance(cfg, scene_dir(cfg)))
    atomic_write_csv(out_dir / "per_image.csv", rows)
    _log(tracker, summary, out_dir)
    return summary


def _log(tracker, summary: dict[str, Any], out_dir: Path) -> None:
    metrics = {f"eval_{k}": v for k, v in summary["mean"].items()} | {"param_count": summary["param_count"]}
    tracker.log_metrics(metrics)
    if "lpips_variant" in summary:
        tracker.set_tags({"nrbench.lpips_variant": summary["lpips_variant"]})
    for name in ("metrics.json", "per_image.csv"):
        tracker.log_artifact(str(out_dir / name), "eval")
    for folder in ("png", "buffers"):
        if (out_dir / folder).is_dir():
            tracker.log_artifacts(str(out_dir / folder), f"eval/{folder}")
