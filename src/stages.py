"""The pipeline stages ``python -m src.run`` dispatches; each reads files and writes files only.

Every stage is runnable alone (DVC calls them one at a time) and writes a JSON summary that carries
the resolved config, the git commit and the fingerprint of the data it read.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError
from src.io.atomic import atomic_directory, atomic_write_json
from src.provenance import provenance

log = logging.getLogger(__name__)


def render(cfg: DictConfig) -> dict:
    """Render the denoising dataset's noisy inputs and references into ``paths.raw``."""
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


def preprocess(cfg: DictConfig) -> dict:
    """Turn the raw EXRs into KPCN inputs/targets: patches (train/val) and full images (val/test)."""
    from src.data.kpcn_buffers import RepairPolicy, load_kpcn_exr
    from src.data.shards import preprocess_dataset

    p = cfg.task.preprocess
    raw, out = Path(cfg.paths.raw), Path(cfg.paths.prepared)
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
        _write_summary(tmp / "preprocess_provenance.json", summary, cfg, raw)
    repaired = f", repaired {len(repairs)} files" if repairs else ""
    print(f"preprocess: {summary['noisy_images']} images, {summary['patches']} patches{repaired} -> {out}")
    return summary


def _write_summary(path: Path, summary: dict, cfg: DictConfig, data_dir: Path) -> None:
    atomic_write_json(path, {"summary": summary, **provenance(cfg, data_dir)})


STAGES: dict[str, Callable[[DictConfig], dict]] = {"render": render, "preprocess": preprocess}


def stages_to_run(cfg: DictConfig) -> list[str]:
    """``stage=all`` runs the task's stages in order; otherwise the one named stage of the task."""
    task_stages = list(cfg.task.stages)
    unknown = [s for s in task_stages if s not in STAGES]
    if unknown:
        raise ConfigError(f"task.stages: unknown stage(s) {unknown}; expected some of {sorted(STAGES)}")
    if cfg.stage == "all":
        return task_stages
    if cfg.stage not in task_stages:
        raise ConfigError(
            f"stage: unknown stage '{cfg.stage}' for task '{cfg.task.name}'; "
            f"expected all or one of {task_stages}"
        )
    return [cfg.stage]
