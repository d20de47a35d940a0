"""The radiance-field task: render (or point at) Blender-format scenes, fit one scene per job, evaluate on
its test views."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from src.provenance import write_summary
from src.schema.nerf import NerfTaskSchema
from src.tasks.base import Task


class NerfTask(Task):
    schema = NerfTaskSchema

    def inputs(self, stage: str, cfg: DictConfig) -> dict[Path, str]:
        from src.data.blender import scene_dir

        producer = "stage=render (or dvc repro; for your own scenes, dataset=blender dataset.root=...)"
        if stage == "train":
            return {scene_dir(cfg) / "transforms_train.json": producer}
        if stage == "eval":
            return {scene_dir(cfg) / f"transforms_{cfg.task.eval.split}.json": producer}
        return {}

    def data_dir(self, cfg: DictConfig) -> Path:
        """The data the runs' `nrbench.data_fingerprint` tag identifies: this job's scene."""
        from src.data.blender import scene_dir

        return scene_dir(cfg)

    def render(self, cfg: DictConfig) -> dict:
        """The procedural multi-view scenes into `paths.scenes` (nothing to do for a user's Blender scenes,
        `dataset=blender`)."""
        scenes = Path(cfg.paths.scenes)
        if "root" in cfg.dataset:
            print(f"render: dataset {cfg.dataset.name} is read from {scenes}; nothing to render")
            return {}
        from src.render.multiview import render_multiview_dataset

        summary = render_multiview_dataset(
            OmegaConf.to_container(cfg.dataset, resolve=True), scenes, cfg.render.variant
        )
        print(
            f"render: {summary.get('scenes_rendered', 0)} scenes rendered, {summary.get('scenes_cached', 0)} "
            f"up to date in {scenes} ({(summary.get('rays_per_second') or 0) / 1e6:.2f} M rays/s)"
        )
        write_summary(Path(cfg.paths.dataset) / "render_summary.json", summary, cfg, scenes)
        return summary

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
