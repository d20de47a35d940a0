"""Evaluation of a denoiser on the held-out full-resolution images (`stage=eval`).

For every image of `task.eval.split` (every scene x noisy spp): denoise it (tiled, so memory stays bounded
on large frames), time it, score it against the reference with `src.metrics.image` (PSNR/SSIM on the
tone-mapped image, relMSE/SMAPE/MSE on linear HDR), and score the noisy input the same way for
reference. Writes `metrics.json` (means overall and per spp), `per_image.csv`, `provenance.json`
(resolved config, git commit, data fingerprint), denoised EXRs and PNG comparison strips under
`task.eval.out_dir`.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from src.data.denoise_dataset import FullImageDataset
from src.data.features import check_trained_features, input_features
from src.eval.common import mean_rows, sync
from src.io.atomic import atomic_write_csv, atomic_write_json
from src.io.exr import write_exr
from src.io.images import save_comparison_strip, write_png
from src.metrics.image import image_metrics, lpips_variant, tonemap
from src.models.denoise.base import Batch, Denoiser, final_color
from src.models.denoise.models import infer_tiled
from src.models.denoise.summary import count_parameters
from src.models.instantiate import build_method
from src.provenance import provenance
from src.train.checkpoint import load_weights
from src.train.device import pick_device

log = logging.getLogger(__name__)

#: Metrics averaged in metrics.json and logged to MLflow as eval_<name> (and eval_noisy_<name>).
SCORES = ("psnr", "ssim", "relmse", "smape", "mse", "lpips", "flip")


def load_denoiser(cfg: DictConfig, device: torch.device) -> Denoiser:
    """Build `cfg.model`; a learned model gets its weights (and whitening buffers) from
    `task.eval.checkpoint`, checked to match the configured architecture."""
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    model = build_method(model_cfg)
    if model.learned:
        state = load_weights(model, model_cfg, cfg.task.eval.checkpoint)
        check_trained_features(state.get("features"), input_features(cfg), cfg.task.eval.checkpoint)
    return model.to(device).eval()


@torch.no_grad()
def denoise_tiled(model: Denoiser, batch: Batch, tile: int, eps: float) -> torch.Tensor:
    """Linear colour (N, 3, H, W) of `batch`, computed in `tile` x `tile` blocks with the model's halo
    (`infer_tiled`: equal to a full-frame pass, memory bounded by the tile), then rebuilt from the
    transformed branches (a per-pixel operation)."""
    return final_color(infer_tiled(model, batch, tile), batch, eps).float()


def _hwc(x: torch.Tensor) -> np.ndarray:
    return x[0].permute(1, 2, 0).cpu().numpy().astype(np.float32)


def _timed_denoise(model: Denoiser, batch: Batch, tile: int, eps: float, device: torch.device):
    sync(device)
    start = time.perf_counter()
    color = denoise_tiled(model, batch, tile, eps)
    sync(device)
    return color, time.perf_counter() - start


def evaluate_denoiser(cfg: DictConfig, tracker) -> dict[str, Any]:
    """Denoise and score every held-out image; returns (and writes) the summary of means."""
    e, m = cfg.task.eval, cfg.metrics
    device = pick_device(cfg.device)
    eps = float(cfg.task.preprocess.eps_albedo)
    model = load_denoiser(cfg, device)
    data = FullImageDataset(cfg.paths.prepared, e.split, features=input_features(cfg))
    out_dir = Path(e.out_dir)
    rows: list[dict[str, Any]] = []
    for i in tqdm(range(len(data)), desc=f"eval {cfg.model.name}", unit="img"):
        item = data[i]
        batch = {k: v[None].to(device) for k, v in item.items() if isinstance(v, torch.Tensor)}
        if i == 0:  # warm-up: one-time costs (allocator, OIDN device, kernel selection) are not runtime
            denoise_tiled(model, batch, int(e.tile), eps)
        color, seconds = _timed_denoise(model, batch, int(e.tile), eps, device)
        images = {
            "noisy": _hwc(item["color"][None]),
            "denoised": _hwc(color),
            "reference": _hwc(item["reference"][None]),
        }
        rows.append(_score(item, images, seconds, m))
        _save_images(out_dir, item, images, e, m)
    summary = {**_summarise(rows), "param_count": count_parameters(model)}
    variant = lpips_variant(m)
    if variant is not None:
        summary["lpips_variant"] = variant
    atomic_write_json(out_dir / "metrics.json", {"model": cfg.model.name, **summary})
    # Beside, not inside, metrics.json: DVC reads every number in a metrics file as a metric.
    atomic_write_json(out_dir / "provenance.json", provenance(cfg, Path(cfg.paths.raw)))
    atomic_write_csv(out_dir / "per_image.csv", rows)
    _log(tracker, summary, out_dir)
    return summary


def _score(
    item: dict[str, Any], images: dict[str, np.ndarray], seconds: float, m: DictConfig
) -> dict[str, Any]:
    """Metrics of the denoised and of the noisy image against the reference, and the runtime."""
    denoised, noisy, reference = images["denoised"], images["noisy"], images["reference"]
    megapixels = reference.shape[0] * reference.shape[1] / 1e6
    row: dict[str, Any] = {"scene": item["scene"], "spp": int(item["spp"])}
    row |= image_metrics(denoised, reference, m)
    row |= {f"noisy_{k}": v for k, v in image_metrics(noisy, reference, m).items()}
    row |= {"ms_per_image": seconds * 1e3, "ms_per_mpixel": seconds * 1e3 / megapixels}
    return row


def _save_images(
    out_dir: Path, item: dict[str, Any], images: dict[str, np.ndarray], e: DictConfig, m: DictConfig
) -> None:
    """EXR of the denoised image, tone-mapped PNGs of noisy/denoised/reference, the comparison strip."""
    denoised = images["denoised"]
    name = f"{item['scene']}-{int(item['spp']):05d}spp"
    if e.save_exr:
        write_exr(
            out_dir / "images" / f"{name}.exr",
            {"R": denoised[..., 0], "G": denoised[..., 1], "B": denoised[..., 2]},
        )
    ldr = {k: tonemap(v, m.tonemap, m.gamma) for k, v in images.items()}
    # Tone-mapped PNGs per image: what report grids compare across models (small, unlike EXRs).
    for kind, image in ldr.items():
        write_png(out_dir / "png" / f"{name}-{kind}.png", image)
    if e.strips:
        labels = {
            "noisy": f"noisy {int(item['spp'])} spp",
            "denoised": "denoised",
            "reference": f"reference {int(item['reference_spp'])} spp",
        }
        panels = [(labels[k], ldr[k]) for k in labels]
        save_comparison_strip(out_dir / "strips" / f"{name}.png", panels, int(e.crop_size), int(e.crop_zoom))


def _summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    per_spp = {
        spp: mean_rows([r for r in rows if r["spp"] == spp]) for spp in sorted({r["spp"] for r in rows})
    }
    return {"images": len(rows), "mean": mean_rows(rows), "per_spp": per_spp}


def _log(tracker, summary: dict[str, Any], out_dir: Path) -> None:
    metrics = {f"eval_{k}": v for k, v in summary["mean"].items()} | {"param_count": summary["param_count"]}
    for spp, means in summary["per_spp"].items():
        keys = (*SCORES, *(f"noisy_{s}" for s in SCORES))
        metrics |= {f"eval_{k}_spp{spp}": means[k] for k in keys if k in means}  # lpips/flip may be off
    tracker.log_metrics(metrics)
    if "lpips_variant" in summary:
        tracker.set_tags({"nrbench.lpips_variant": summary["lpips_variant"]})
    tracker.log_artifact(str(out_dir / "metrics.json"), "eval")
    tracker.log_artifact(str(out_dir / "per_image.csv"), "eval")
    for folder in ("strips", "png"):
        if (out_dir / folder).is_dir():
            tracker.log_artifacts(str(out_dir / folder), f"eval/{folder}")
