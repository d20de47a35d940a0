"""The Monte Carlo denoising task: render (or read) noisy and reference EXRs, prepare them into network
inputs, train a denoiser, evaluate it on held-out data. What each stage does to the data is the data
kind's (`dataset._target_`, `src/kinds/`: still images, image sequences); this task checks the kind is a
denoising one, runs the stages and prints their one-line summaries."""

from __future__ import annotations

from omegaconf import DictConfig

from src.kinds.denoising import DenoisingKind
from src.models.denoise.base import Denoiser
from src.schema.denoise import DenoiseTaskSchema
from src.tasks.base import Task


class DenoiseTask(Task):
    schema = DenoiseTaskSchema
    kinds = DenoisingKind
    methods = Denoiser

    def preprocess(self, cfg: DictConfig) -> dict:
        return self.kind.preprocess(cfg)

    def train(self, cfg: DictConfig, tracker) -> dict:
        """Fit the denoiser on the kind's data (`src.train.trainer`)."""
        from src.train.trainer import train_denoiser

        return train_denoiser(cfg, tracker, self.kind)

    def select_features(self, cfg: DictConfig, tracker) -> dict:
        """The feature-selection probe and its greedy forward selection (`src.train.select_features`)."""
        from src.train.select_features import select_features

        return select_features(cfg, tracker, self.kind)

    def evaluate(self, cfg: DictConfig, tracker) -> dict:
        """Score the method on the kind's held-out items (`src.eval.denoise_eval`); print its line."""
        from src.eval.denoise_eval import evaluate_denoiser

        summary = evaluate_denoiser(cfg, tracker, self.kind)
        mean = summary["mean"]
        flicker = (
            f", flicker {mean['temporal']:.4f} (noisy {mean['noisy_temporal']:.4f})"
            if "temporal" in mean
            else ""
        )
        print(
            f"eval: {cfg.model.name} on {summary['images']} images{flicker}: PSNR {mean['psnr']:.2f} dB "
            f"(noisy {mean['noisy_psnr']:.2f}), SSIM {mean['ssim']:.4f}, relMSE (Bako) {mean['relmse']:.5f} "
            f"(noisy {mean['noisy_relmse']:.5f}), {mean['ms_per_mpixel']:.1f} ms/MP "
            f"-> {cfg.task.eval.out_dir}"
        )
        return summary

    def model_summary(self, model, model_cfg: dict) -> str:
        from src.models.denoise.summary import model_summary

        return model_summary(model, model_cfg)

    def training_summary(self, model, cfg: DictConfig) -> str:
        return self.kind.training_summary(model, cfg)
