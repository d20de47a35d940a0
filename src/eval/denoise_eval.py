"""Evaluation of a denoiser on the held-out full-resolution images (`stage=eval`).

For every image of `task.eval.split` (every scene x noisy spp): denoise it (tiled, so memory stays bounded
on large frames), time it, score it against the reference with `src.metrics.image` (PSNR/SSIM on the
tone-mapped image, relMSE/SMAPE/MSE on linear HDR), and score the noisy input the same way for
reference. relMSE comes in two conventions: `relmse` (Bako et al. 2017: mean over pixels and channels)
and `relmse_spp` (Davletaliyev 2016, Eq. 3.5: summed over channels, times spp/2), with `relmse_ratio`,
the denoised image's Eq. 3.5 value over the noisy one's (the GP thesis's fitness term).

Writes `metrics.json` (means overall and per spp), `per_image.csv`, `provenance.json` (resolved config,
git commit, data fingerprint), denoised EXRs and PNG comparison strips under `task.eval.out_dir`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from src.data.denoise_dataset import FullImageDataset
from src.data.features import check_trained_features, input_features
from src.eval.common import mean_rows
from src.eval.loop import Evaluation
from src.io.exr import write_exr
from src.io.images import save_comparison_strip, write_png
from src.metrics.image import image_metrics, relmse_spp, tonemap
from src.models.denoise.base import Batch, Denoiser, final_color
from src.models.denoise.models import infer_tiled

log = logging.getLogger(__name__)

#: Metrics averaged in metrics.json and logged to MLflow as eval_<name> (and eval_noisy_<name>); `temporal`
#: (flicker) only where there are sequences (`src.eval.sequence_eval`).
SCORES = ("psnr", "ssim", "relmse", "relmse_spp", "relmse_ratio", "smape", "mse", "lpips", "flip", "temporal")


@torch.no_grad()
def denoise_tiled(model: Denoiser, batch: Batch, tile: int, eps: float) -> torch.Tensor:
    """Linear colour (N, 3, H, W) of `batch`, computed in `tile` x `tile` blocks with the model's halo
    (`infer_tiled`: equal to a full-frame pass, memory bounded by the tile), then rebuilt from the
    transformed branches (a per-pixel operation)."""
    return final_color(infer_tiled(model, batch, tile), batch, eps).float()


def _hwc(x: torch.Tensor) -> np.ndarray:
    return x[0].permute(1, 2, 0).cpu().numpy().astype(np.float32)


def gp_relmse(
    denoised: np.ndarray, noisy: np.ndarray, reference: np.ndarray, spp: int, eps: float
) -> dict[str, float]:
    """The GP thesis's relMSE (Davletaliyev 2016, Eq. 3.5) of the denoised and the noisy image, and their
    ratio: that image's term of the thesis's fitness (its scenes' ratios averaged)."""
    ours, noisy_value = relmse_spp(denoised, reference, spp, eps), relmse_spp(noisy, reference, spp, eps)
    ratio = ours / noisy_value if noisy_value > 0 else float("nan")
    return {"relmse_spp": ours, "noisy_relmse_spp": noisy_value, "relmse_ratio": ratio}


class OnDevice(Sequence):
    """The held-out items of `data` with their tensors on the device under "batch" (loaded before the
    timed call): a still image as a batch of one, a sequence's frames as the batch (`as_batch_of_one`
    False)."""

    def __init__(self, data, device: torch.device, as_batch_of_one: bool = True) -> None:
        self.data, self.device, self.single = data, device, as_batch_of_one

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, i: int) -> dict[str, Any]:
        item = self.data[i]
        tensors = {k: v for k, v in item.items() if isinstance(v, torch.Tensor)}
        batch = {k: (v[None] if self.single else v).to(self.device) for k, v in tensors.items()}
        return {"item": item, "batch": batch}


def held_out_images(cfg: DictConfig, model: Denoiser) -> FullImageDataset:
    """The full images of `task.eval.split`, after checking from their index that they hold what `model`
    reads (`Denoiser.check_batch_keys`: a one-line error before any image is denoised or file written)."""
    data = FullImageDataset(cfg.paths.prepared, cfg.task.eval.split, features=input_features(cfg))
    model.check_batch_keys(data.batch_keys)
    return data


class DenoiseEvaluation(Evaluation):
    """Every image of `task.eval.split` (every scene x noisy spp), denoised in tiles."""

    artifact_folders = ("strips", "png")

    def __init__(self, cfg: DictConfig, tracker) -> None:
        super().__init__(cfg, tracker)
        self.features = input_features(cfg)
        if self.checkpoint is not None:
            check_trained_features(self.checkpoint.get("features"), self.features, cfg.task.eval.checkpoint)
        self.eps = float(cfg.task.preprocess.eps_albedo)

    def items(self) -> Sequence[dict[str, Any]]:
        data = held_out_images(self.cfg, self.model)
        return OnDevice(data, self.device)

    def infer(self, item: dict[str, Any]) -> torch.Tensor:
        return denoise_tiled(self.model, item["batch"], int(self.cfg.task.eval.tile), self.eps)

    def data_dir(self) -> Path:
        return Path(self.cfg.paths.raw)

    def untimed(self, item: dict[str, Any], output: torch.Tensor) -> dict[str, np.ndarray]:
        return {
            "noisy": _hwc(item["item"]["color"][None]),
            "denoised": _hwc(output),
            "reference": _hwc(item["item"]["reference"][None]),
        }

    def score(self, item: dict[str, Any], images: dict[str, np.ndarray], seconds: float) -> dict[str, Any]:
        """Metrics of the denoised and of the noisy image against the reference, and the runtime."""
        denoised, noisy, reference = images["denoised"], images["noisy"], images["reference"]
        m = self.cfg.metrics
        megapixels = reference.shape[0] * reference.shape[1] / 1e6
        row: dict[str, Any] = {"scene": item["item"]["scene"], "spp": int(item["item"]["spp"])}
        row |= image_metrics(denoised, reference, m)
        row |= {f"noisy_{k}": v for k, v in image_metrics(noisy, reference, m).items()}
        row |= gp_relmse(denoised, noisy, reference, row["spp"], float(m.relmse_eps))
        row |= {"ms_per_image": seconds * 1e3, "ms_per_mpixel": seconds * 1e3 / megapixels}
        return row

    def save_outputs(self, item: dict[str, Any], images: dict[str, np.ndarray]) -> None:
        _save_images(self.out_dir, item["item"], images, self.cfg.task.eval, self.cfg.metrics)

    def summarise(self, rows: list[dict[str, Any]]) -> dict[str, Any]:
        per_spp = {
            spp: mean_rows([r for r in rows if r["spp"] == spp]) for spp in sorted({r["spp"] for r in rows})
        }
        return {**super().summarise(rows), "per_spp": per_spp}

    def logged_metrics(self, summary: dict[str, Any]) -> dict[str, float]:
        metrics = super().logged_metrics(summary)
        for spp, means in summary["per_spp"].items():
            keys = (*SCORES, *(f"noisy_{s}" for s in SCORES))
            metrics |= {f"eval_{k}_spp{spp}": means[k] for k in keys if k in means}  # lpips/flip may be off
        return metrics


def evaluate_denoiser(cfg: DictConfig, tracker) -> dict[str, Any]:
    """Denoise and score every held-out image; returns (and writes) the summary of means."""
    return DenoiseEvaluation(cfg, tracker).run(desc=f"eval {cfg.model.name}")


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
