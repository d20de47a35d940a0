"""The pipeline stages ``python -m src.run`` dispatches; each reads files and writes files only.

Every stage is runnable alone (DVC calls them one at a time) and writes a JSON summary that carries
the resolved config, the git commit and the fingerprint of the data it read.
"""

from __future__ import annotations

import hashlib
import json
import logging
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError
from src.io.atomic import atomic_directory, atomic_write_json, atomic_write_text
from src.provenance import data_fingerprint, provenance, result_config

log = logging.getLogger(__name__)
PREPROCESS_PROVENANCE = "preprocess_provenance.json"


def render(cfg: DictConfig, tracker=None) -> dict:
    """Render the task's dataset: the denoising EXRs into `paths.raw`, or the NeRF multi-view scenes
    into `paths.scenes` (nothing to do for a user's Blender scenes, `dataset=blender`)."""
    if cfg.task.name == "nerf":
        return _render_multiview(cfg)
    from src.render.render_dataset import render_denoise_dataset

    raw = Path(cfg.paths.raw)
    summary = render_denoise_dataset(
        OmegaConf.to_container(cfg.dataset, resolve=True), raw, cfg.render.variant
    )
    if summary["samples_per_second"]:
        print(
            f"render: {summary['files_rendered']} files ({summary['files_cached']} cached) in "
            f"{summary['render_seconds']:.1f} s, {summary['samples_per_second'] / 1e6:.2f} M samples/s "
            f"[{summary['variant']}]"
        )
    else:
        print(f"render: all {summary['files_cached']} files up to date in {raw}")
    _write_summary(Path(cfg.paths.dataset) / "render_summary.json", summary, cfg, raw)
    return summary


def _render_multiview(cfg: DictConfig) -> dict:
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
    _write_summary(Path(cfg.paths.dataset) / "render_summary.json", summary, cfg, scenes)
    return summary


def _preprocess_key(cfg: DictConfig, raw: Path) -> str:
    """What the prepared data depends on: the preprocessing settings and the raw data's fingerprint."""
    settings = json.dumps(OmegaConf.to_container(cfg.task.preprocess, resolve=True), sort_keys=True)
    return hashlib.sha256(f"{settings}|{data_fingerprint(raw)}".encode()).hexdigest()[:16]


def _cached_preprocess(out: Path, key: str) -> dict | None:
    try:
        record = json.loads((out / PREPROCESS_PROVENANCE).read_text())
    except (OSError, ValueError):
        return None
    return record["summary"] if record.get("cache_key") == key else None


def preprocess(cfg: DictConfig, tracker=None) -> dict:
    """Turn the raw EXRs into KPCN inputs/targets: patches (train/val) and full images (val/test).

    Skipped when the prepared directory was made from the same settings and raw data (each job of a
    multirun would otherwise redo it)."""
    from src.data.kpcn_buffers import RepairPolicy, load_kpcn_exr
    from src.data.shards import preprocess_dataset

    p = cfg.task.preprocess
    raw, out = Path(cfg.paths.raw), Path(cfg.paths.prepared)
    key = _preprocess_key(cfg, raw)
    cached = _cached_preprocess(out, key)
    if cached is not None:
        print(f"preprocess: up to date in {out}")
        return cached
    policy = RepairPolicy(**OmegaConf.to_container(p.repair, resolve=True))
    repairs: dict[str, str] = {}

    def load(path: Path):
        buffers, report = load_kpcn_exr(path, repair=policy)
        if report.total:
            repairs[path.name] = report.summary()
        return buffers

    with atomic_directory(out) as tmp:
        summary = preprocess_dataset(
            raw,
            tmp,
            eps=p.eps_albedo,
            patch_size=p.patch_size,
            patches_per_image=p.patches_per_image,
            split_fractions=dict(p.split),
            split_seed=p.split_seed,
            sample_seed=p.sample_seed,
            candidates_factor=p.candidates_factor,
            min_keep_prob=p.min_keep_prob,
            min_distance=p.min_distance * p.patch_size,
            whiten_eps=p.whiten_eps,
            importance_percentile=p.importance_percentile,
            load_fn=load,
        )
        summary["repairs"] = repairs
        _write_summary(tmp / PREPROCESS_PROVENANCE, summary, cfg, raw, cache_key=key)
    repaired = f", repaired {len(repairs)} files" if repairs else ""
    print(f"preprocess: {summary['noisy_images']} images, {summary['patches']} patches{repaired} -> {out}")
    return summary


def train(cfg: DictConfig, tracker) -> dict:
    """Fit the learned model: a denoiser on the prepared patches, or a radiance field on one scene
    (non-learned baselines have nothing to fit)."""
    if not cfg.model.learned:
        print(f"train: {cfg.model.name} is not learned; nothing to train")
        return {}
    if cfg.task.name == "nerf":
        from src.train.nerf_trainer import scene_dir
        from src.train.nerf_trainer import train_nerf as fit

        data = scene_dir(cfg)
    else:
        from src.train.trainer import train_denoiser as fit

        data = Path(cfg.paths.raw)
    tracker.set_tags({"nrbench.data_fingerprint": data_fingerprint(data)})
    summary = fit(cfg, tracker)
    tracker.log_artifact(summary["checkpoint"], "checkpoints")
    print(
        f"train: {cfg.model.name} {summary['steps']} steps in {summary['train_time_s']:.1f} s "
        f"-> {summary['checkpoint']}"
    )
    return summary


def evaluate(cfg: DictConfig, tracker) -> dict:
    """Score the model on the held-out data (denoised test images, or rendered test views); log metrics
    and images."""
    if cfg.task.name == "nerf":
        return _evaluate_nerf(cfg, tracker)
    from src.eval.denoise_eval import evaluate_denoiser

    tracker.set_tags({"nrbench.data_fingerprint": data_fingerprint(Path(cfg.paths.raw))})
    summary = evaluate_denoiser(cfg, tracker)
    mean = summary["mean"]
    print(
        f"eval: {cfg.model.name} on {summary['images']} images: PSNR {mean['psnr']:.2f} dB "
        f"(noisy {mean['noisy_psnr']:.2f}), SSIM {mean['ssim']:.4f}, relMSE {mean['relmse']:.5f} "
        f"(noisy {mean['noisy_relmse']:.5f}), {mean['ms_per_mpixel']:.1f} ms/MP -> {cfg.task.eval.out_dir}"
    )
    return summary


def _evaluate_nerf(cfg: DictConfig, tracker) -> dict:
    from src.eval.nerf_eval import evaluate_nerf
    from src.train.nerf_trainer import scene_dir

    tracker.set_tags({"nrbench.data_fingerprint": data_fingerprint(scene_dir(cfg))})
    summary = evaluate_nerf(cfg, tracker)
    mean = summary["mean"]
    lpips = f", LPIPS {mean['lpips']:.4f}" if "lpips" in mean else ""
    print(
        f"eval: {cfg.model.name} on {cfg.task.scene}, {summary['images']} views: PSNR {mean['psnr']:.2f} dB, "
        f"SSIM {mean['ssim']:.4f}{lpips}, {mean['rays_per_s'] / 1e3:.1f} k rays/s -> {cfg.task.eval.out_dir}"
    )
    return summary


def report(cfg: DictConfig, tracker=None) -> dict:
    """Tables, figures and an HTML page from the logged MLflow runs (`report.*` selects them). Inside a
    multirun the sweep's callback writes one report over all its jobs when they are done instead."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        print("report: written once, over all jobs, when the sweep ends")
        return {}
    if not cfg.tracking.enabled:
        print("report: tracking.enabled is false, so there are no logged runs to report on")
        return {}
    from src.report.build import build_report, report_line

    summary = build_report(cfg)
    print(report_line(summary), flush=True)
    return summary


def print_model_summary(cfg: DictConfig, tracker=None) -> dict:
    """Print the model's architecture and parameter count (and FLOPs per pixel or per ray); trains
    nothing."""
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    if cfg.task.name == "nerf":
        from src.models.instantiate import build_method
        from src.models.nerf.models import nerf_model_summary

        print(nerf_model_summary(build_method(model_cfg), model_cfg))
        return {}
    from src.models.denoise.summary import model_summary
    from src.models.instantiate import build_method

    print(model_summary(build_method(model_cfg), model_cfg))
    return {}


def write_result_config(cfg: DictConfig, tracker=None) -> dict:
    """Write what decides this job's results (`provenance.result_config`) to `<paths.run_dir>/params.yaml`.

    DVC's train/eval stages depend on this file instead of on `conf/`: it changes only when a value the
    job uses changes, so editing one model's config reruns that model's stages and no other."""
    path = Path(cfg.paths.run_dir) / "params.yaml"
    atomic_write_text(path, OmegaConf.to_yaml(result_config(cfg), sort_keys=True))
    print(f"config: {cfg.model.name} -> {path}")
    return {}


def _write_summary(path: Path, summary: dict, cfg: DictConfig, data_dir: Path, **extra) -> None:
    atomic_write_json(path, {"summary": summary, **extra, **provenance(cfg, data_dir)})


STAGES: dict[str, Callable[..., dict]] = {
    "render": render,
    "preprocess": preprocess,
    "train": train,
    "eval": evaluate,
    "report": report,
    "summary": print_model_summary,
    "config": write_result_config,
}
#: Stages that run outside a task's pipeline and log nothing.
STANDALONE = ("summary", "config")
#: Stages whose results go to MLflow (one run per job).
TRACKED = ("train", "eval")
#: Stages that read the logged runs, so they run after the job's own MLflow run has finished.
AFTER_RUN = ("report",)


def stages_to_run(cfg: DictConfig) -> list[str]:
    """``stage=all`` runs the task's stages in order; otherwise the one named stage of the task."""
    task_stages = list(cfg.task.stages)
    unknown = [s for s in task_stages if s not in STAGES]
    if unknown:
        raise ConfigError(f"task.stages: unknown stage(s) {unknown}; expected some of {sorted(STAGES)}")
    if cfg.stage == "all":
        return task_stages
    if cfg.stage in STANDALONE:
        return [cfg.stage]
    if cfg.stage not in task_stages:
        raise ConfigError(
            f"stage: unknown stage '{cfg.stage}' for task '{cfg.task.name}'; "
            f"expected all, one of {task_stages}, or {' / '.join(STANDALONE)}"
        )
    return [cfg.stage]
