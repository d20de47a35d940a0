"""The radiance-field task: render (or point at) Blender-format scenes, fit one scene per job, evaluate on
its test views. The scenes are the data kind's (`dataset._target_`, `src/kinds/multiview.py`)."""

from __future__ import annotations

from omegaconf import DictConfig

from src.kinds.multiview import MultiViewKind
from src.models.nerf.models import NerfModelBase
from src.schema.nerf import NerfTaskSchema
from src.tasks.base import Task


class NerfTask(Task):
    schema = NerfTaskSchema
    kinds = MultiViewKind
    methods = NerfModelBase

    def train(self, cfg: DictConfig, tracker) -> dict:
        from src.train.nerf_trainer import train_nerf

        return train_nerf(cfg, tracker)

    def evaluate(self, cfg: DictConfig, tracker) -> dict:
        from src.eval.nerf_eval import evaluate_nerf

        summary = evaluate_nerf(cfg, tracker)
        mean = summary["mean"]
        lpips = f", LPIPS {mean['lpips']:.4f}" if "lpips" in mean else ""
        print(
            f"eval: {cfg.model.name} on {cfg.task.scene}, {summary['images']} views: "
            f"PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.4f}{lpips}, "
            f"{mean['rays_per_s'] / 1e3:.1f} k rays/s -> {cfg.task.eval.out_dir}"
        )
        return summary

    def model_summary(self, model, model_cfg: dict) -> str:
        from src.models.nerf.summary import nerf_model_summary

        return nerf_model_summary(model, model_cfg)

    def training_summary(self, model, cfg: DictConfig) -> str:
        """The training step's estimated activation memory (`task.train.micro_batch_rays` sizes it)."""
        from src.models.nerf.summary import activation_line

        train = cfg.task.train
        return activation_line(model, int(train.batch_size), train.get("micro_batch_rays"))
