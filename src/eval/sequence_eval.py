"""Evaluation on the volumetric sequences (`stage=eval dataset=volumetric`): every held-out sequence
(scene x noisy spp) denoised frame by frame, scored per frame and for flicker.

Each frame goes through the model alone (tiled, `infer_tiled`), whatever the model: the U-Net KPCN, the
KPCN family on frames, OIDN or a cross-bilateral filter, so all are compared on equal terms. A row of
`per_image.csv` is one sequence: the per-frame metrics of `src.metrics.image` averaged over its frames
(PSNR/SSIM/LPIPS tone-mapped, relMSE/SMAPE/MSE/FLIP linear, the GP thesis's relMSE and ratio), the
temporal-stability metric `temporal` of the whole sequence (`src.metrics.temporal`: mean |Δt output -
Δt reference|, tone-mapped; flicker), each also for the noisy input (`noisy_*`), and the runtime per frame
and per megapixel. The rest (means per spp, metrics.json, MLflow) is the still-image evaluation's.

Images: the denoised frames as EXR (`save_exr`) and tone-mapped PNGs, and a comparison strip of the
middle frame (`strips`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from src.data.sequence_dataset import SequenceDataset
from src.data.volume_features import run_volume_features
from src.eval.denoise_eval import DenoiseEvaluation, OnDevice, _save_images, gp_relmse
from src.eval.loop import Evaluation
from src.metrics.image import image_metrics
from src.metrics.temporal import temporal_error
from src.models.denoise.models import infer_tiled


def _frames_hwc(x: torch.Tensor) -> np.ndarray:
    """(F, 3, H, W) -> (F, H, W, 3) float32 numpy."""
    return x.permute(0, 2, 3, 1).cpu().numpy().astype(np.float32)


def _check_trained(trained: list[str] | None, configured: list[str] | None, checkpoint: str) -> None:
    from src.errors import DataError

    if trained != configured:
        raise DataError(
            f"{checkpoint}: trained with task.volume_features={trained} (null: all), configured "
            f"{configured}; evaluate with the features it was trained on"
        )


class SequenceEvaluation(DenoiseEvaluation):
    """Every sequence of `task.eval.split`, denoised frame by frame in tiles (module docstring)."""

    unit = "seq"

    def __init__(self, cfg: DictConfig, tracker) -> None:
        Evaluation.__init__(self, cfg, tracker)
        self.features = run_volume_features(cfg)
        if self.checkpoint is not None and "features" in self.checkpoint:
            _check_trained(self.checkpoint["features"], self.features, str(cfg.task.eval.checkpoint))
        self.eps = float(cfg.task.preprocess.eps_albedo)

    def items(self) -> Sequence[dict[str, Any]]:
        data = SequenceDataset(self.cfg.paths.prepared, self.cfg.task.eval.split, features=self.features)
        return OnDevice(data, self.device, as_batch_of_one=False)

    @torch.no_grad()
    def infer(self, item: dict[str, Any]) -> torch.Tensor:
        frames, tile = item["batch"], int(self.cfg.task.eval.tile)
        count = frames["color"].shape[0]
        outputs = [
            infer_tiled(self.model, {k: v[f : f + 1] for k, v in frames.items()}, tile)["color"].float()
            for f in range(count)
        ]
        return torch.cat(outputs)

    def untimed(self, item: dict[str, Any], output: torch.Tensor) -> dict[str, np.ndarray]:
        return {
            "noisy": _frames_hwc(item["item"]["color"]),
            "denoised": _frames_hwc(output),
            "reference": _frames_hwc(item["item"]["reference"]),
        }

    def score(self, item: dict[str, Any], images: dict[str, np.ndarray], seconds: float) -> dict[str, Any]:
        """Per-frame metrics averaged over the frames, the sequence's flicker, the runtime per frame."""
        denoised, noisy, reference = images["denoised"], images["noisy"], images["reference"]
        m, spp = self.cfg.metrics, int(item["item"]["spp"])
        frames, height, width = reference.shape[:3]
        per_frame = []
        for f in range(frames):
            row = image_metrics(denoised[f], reference[f], m)
            row |= {f"noisy_{k}": v for k, v in image_metrics(noisy[f], reference[f], m).items()}
            row |= gp_relmse(denoised[f], noisy[f], reference[f], spp, float(m.relmse_eps))
            per_frame.append(row)
        means = {k: float(np.mean([r[k] for r in per_frame])) for k in per_frame[0]}
        flicker = {
            "temporal": temporal_error(denoised, reference, m.tonemap, m.gamma),
            "noisy_temporal": temporal_error(noisy, reference, m.tonemap, m.gamma),
        }
        ms_per_frame = seconds * 1e3 / frames
        timing = {"ms_per_image": ms_per_frame, "ms_per_mpixel": ms_per_frame / (height * width / 1e6)}
        return {"scene": item["item"]["scene"], "spp": spp, "frames": frames, **means, **flicker, **timing}

    def save_outputs(self, item: dict[str, Any], images: dict[str, np.ndarray]) -> None:
        """Every frame's EXR and PNGs (as a still image named `<scene>-f<FFFF>`), the middle frame's strip."""
        e = self.cfg.task.eval
        frames = images["reference"].shape[0]
        for f in range(frames):
            frame_item = {**item["item"], "scene": f"{item['item']['scene']}-f{f:04d}"}
            options = e if f == frames // 2 else OmegaConf.merge(e, {"strips": False})
            _save_images(
                self.out_dir, frame_item, {k: v[f] for k, v in images.items()}, options, self.cfg.metrics
            )

    def data_dir(self) -> Path:
        return Path(self.cfg.paths.raw)


def evaluate_sequences(cfg: DictConfig, tracker) -> dict[str, Any]:
    """Denoise and score every held-out sequence; returns (and writes) the summary of means."""
    return SequenceEvaluation(cfg, tracker).run(desc=f"eval {cfg.model.name}")
