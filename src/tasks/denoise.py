"""The Monte Carlo denoising task: render the KPCN-buffer EXRs, preprocess them into network inputs and
patches, train a denoiser, evaluate it on the test images."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from src.data.features import CANDIDATE_CHANNELS
from src.data.prepared_check import check_prepared_is_current
from src.data.sequence_patches import FRAMES_KEY
from src.errors import ConfigError
from src.io.atomic import atomic_directory
from src.provenance import data_fingerprint, write_summary
from src.schema.denoise import DenoiseTaskSchema
from src.tasks.base import Task

PREPROCESS_PROVENANCE = "preprocess_provenance.json"
#: `task.preprocess` keys only `dataset=volumetric` reads (`src.data.volume_shards`).
VOLUME_ONLY_KEYS = ("volume_transform", "sequence_frames", "patches_per_sequence")


def _cache_key(settings: dict, raw: Path, stored: Sequence[str]) -> str:
    """What prepared data depend on: the preprocessing settings, the raw data's fingerprint and the
    stored channels (prepared folders of an older channel set are made again)."""
    text = json.dumps(settings, sort_keys=True)
    return hashlib.sha256(f"{text}|{data_fingerprint(raw)}|{','.join(stored)}".encode()).hexdigest()[:16]


def _preprocess_key(cfg: DictConfig, raw: Path) -> str:
    """The still images' cache key: every `task.preprocess` setting but the volumetric-only ones (so
    adding or changing those leaves prepared still-image folders valid), the stored KPCN inputs and the
    other stored tensors (`SHARD_CHANNEL_NAMES`: folders made before the GP features were added rebuild)."""
    settings = OmegaConf.to_container(cfg.task.preprocess, resolve=True)
    settings = {k: v for k, v in settings.items() if k not in VOLUME_ONLY_KEYS}
    from src.data.shards import SHARD_CHANNEL_NAMES  # lazy: torch

    return _cache_key(settings, raw, (*CANDIDATE_CHANNELS, *SHARD_CHANNEL_NAMES))


def _volumetric_key(cfg: DictConfig, raw: Path) -> tuple[dict, str]:
    """The volumetric `preprocess_volume_dataset` settings and their cache key (with the repair policy)."""
    from src.data.volume_features import VOLUME_CANDIDATE_CHANNELS
    from src.data.volume_shards import SEQUENCE_KEYS

    p = OmegaConf.to_container(cfg.task.preprocess, resolve=True)
    settings = {
        **{k: p[k] for k in ("patch_size", "patches_per_sequence", "sequence_frames", "volume_transform")},
        "split_fractions": p["split"],
        **{k: p[k] for k in ("split_seed", "sample_seed", "candidates_factor", "min_keep_prob")},
        "min_distance": p["min_distance"] * p["patch_size"],
        **{k: p[k] for k in ("importance", "importance_window", "importance_percentile", "whiten_eps")},
    }
    key = _cache_key({**settings, "repair": p["repair"]}, raw, (*SEQUENCE_KEYS, *VOLUME_CANDIDATE_CHANNELS))
    return settings, key


def _prepared_key(cfg: DictConfig, raw: Path) -> str:
    """The cache key `stage=preprocess` gives `paths.prepared` for this config and the raw data in `raw`."""
    return _volumetric_key(cfg, raw)[1] if cfg.dataset.name == "volumetric" else _preprocess_key(cfg, raw)


def _cached_preprocess(out: Path, key: str) -> dict | None:
    try:
        record = json.loads((out / PREPROCESS_PROVENANCE).read_text())
    except (OSError, ValueError):
        return None
    return record["summary"] if record.get("cache_key") == key else None


def _check_dataset_stage(stage: str, cfg: DictConfig) -> None:
    """A one-line ConfigError for a stage this dataset cannot run: feature selection outside the
    volumetric sequences, or a preprocessing window longer than its sequences."""
    volumetric = cfg.dataset.name == "volumetric"
    if stage == "select_features" and not volumetric:
        raise ConfigError(
            f"stage=select_features: the feature selection chooses among the volumetric candidates "
            f"(task.volume_features); dataset={cfg.dataset.name} has a fixed feature list (task.features); "
            "run it with dataset=volumetric"
        )
    if not volumetric:
        return
    k, frames = cfg.task.preprocess.sequence_frames, cfg.dataset.frames
    if stage == "preprocess" and k > frames:
        raise ConfigError(
            f"{FRAMES_KEY}={k} is more than the dataset.frames={frames} frames of each volumetric sequence"
        )


def _check_model_dataset(stage: str, cfg: DictConfig) -> None:
    """A one-line ConfigError for training or evaluating a model of the volumetric frame batches (its
    builder's `frame_batch`: the U-Net KPCN, `conf/model_dataset/*_volumetric.yaml`) on a still-image
    dataset, whose diffuse/specular batches it cannot read."""
    if stage not in ("train", "eval") or cfg.dataset.name == "volumetric":
        return
    from src.models.instantiate import resolve_target

    if getattr(resolve_target(cfg.model), "frame_batch", False):
        raise ConfigError(
            f"model={cfg.model.name} reads the volumetric frame batches: stage={stage} needs "
            f"dataset=volumetric, not dataset={cfg.dataset.name}"
        )


def held_out_index(cfg: DictConfig) -> Path:
    """The index of the prepared full images that `stage=eval` reads (`task.eval.split`)."""
    return Path(cfg.paths.prepared) / "full" / str(cfg.task.eval.split) / "index.json"


def _check_held_out_inputs(stage: str, cfg: DictConfig) -> None:
    """At job start of a still-image `stage=eval` whose prepared images exist: the one-line error of a
    method that needs a buffer they lack (e.g. a GP filter's world position on real KPCN data), before
    any run is opened or file written. (When an earlier stage of the job makes them, the eval stage checks
    the same when it opens them.)"""
    if stage != "eval" or cfg.dataset.name == "volumetric":
        return
    if not held_out_index(cfg).is_file():
        return
    from src.eval.denoise_eval import held_out_images
    from src.models.instantiate import build_method

    held_out_images(cfg, build_method(OmegaConf.to_container(cfg.model, resolve=True)))


def _render_volumetric(ds: dict, raw: Path, variant: str, summary_path: Path) -> tuple[dict, Path]:
    """Render the volumetric sequences (or the `render_scenes` / `render_frames` subset a fanned-out job
    was given); returns the summary and where to write it: one file per subset, so jobs keep theirs."""
    from src.render.volume_dataset import render_volumetric_dataset

    scenes, frames = ds.get("render_scenes"), ds.get("render_frames")
    summary = render_volumetric_dataset(ds, raw, variant, scenes=scenes, frames=frames)
    if scenes is not None or frames is not None:
        tag = hashlib.sha256(json.dumps([scenes, frames]).encode()).hexdigest()[:8]
        summary_path = summary_path.with_name(f"render_summary-{tag}.json")
    return summary, summary_path


def _preprocess_volumetric(cfg: DictConfig) -> dict:
    """The volumetric sequences into k-frame samples (train/val) and whole sequences (val/test)
    (`src.data.volume_shards`); skipped when made from the same settings, repair policy and raw data."""
    from src.data.exr_buffers import RepairPolicy
    from src.data.volume_buffers import load_volume_exr
    from src.data.volume_shards import preprocess_volume_dataset

    p = OmegaConf.to_container(cfg.task.preprocess, resolve=True)
    raw, out = Path(cfg.paths.raw), Path(cfg.paths.prepared)
    settings, key = _volumetric_key(cfg, raw)
    cached = _cached_preprocess(out, key)
    if cached is not None:
        print(f"preprocess: up to date in {out}")
        return cached
    policy = RepairPolicy(**p["repair"])
    repairs: dict[str, str] = {}

    def load(path: Path, buffers):
        loaded, report = load_volume_exr(path, repair=policy, buffers=buffers)
        if report.total:
            repairs[path.name] = report.summary()
        return loaded

    with atomic_directory(out) as tmp:
        summary = preprocess_volume_dataset(raw, tmp, **settings, load_fn=load)
        summary["repairs"] = repairs
        write_summary(tmp / PREPROCESS_PROVENANCE, summary, cfg, raw, cache_key=key)
    repaired = f", repaired {len(repairs)} files" if repairs else ""
    samples, full = summary["samples"], summary["full_sequences"]
    print(
        f"preprocess: {summary['noisy_sequences']} noisy sequences: {samples['train']} train / "
        f"{samples['val']} val samples of {settings['sequence_frames']} frames, {full['val']} val / "
        f"{full['test']} test whole sequences{repaired} in {summary['seconds']:.1f} s -> {out}"
    )
    return summary


class DenoiseTask(Task):
    schema = DenoiseTaskSchema

    def inputs(self, stage: str, cfg: DictConfig) -> dict[Path, str]:
        _check_dataset_stage(stage, cfg)
        prepared, preprocessed = Path(cfg.paths.prepared), "stage=preprocess (or dvc repro)"
        if stage == "preprocess":
            return {Path(cfg.paths.raw): "stage=render (or dvc repro)"}
        if stage in ("train", "select_features"):
            return {prepared / "patches" / "train" / "index.json": preprocessed}
        if stage == "eval":
            return {held_out_index(cfg): preprocessed}
        return {}

    def data_dir(self, cfg: DictConfig) -> Path:
        """The data the runs' `nrbench.data_fingerprint` tag identifies: the raw EXRs."""
        return Path(cfg.paths.raw)

    def resolve_at_job_start(self, cfg: DictConfig) -> None:
        """`task.feature_selection.size` = k: `task.volume_features` becomes the start set plus the first k
        features of the selection stage's output (or k drawn at random), so the model's `in_channels`
        follows; null leaves the configured features. The chosen names get the schema's check (it ran
        before they were known): a hand-edited selection file is one line, not a failure later."""
        if cfg.task.feature_selection.size is not None:
            from src.data.volume_features import volume_feature_channels
            from src.train.select_features import features_for_size

            features = features_for_size(cfg.task.feature_selection)
            volume_feature_channels(features)
            cfg.task.volume_features = features

    def check_stages(self, stages: list[str], cfg: DictConfig) -> None:
        """Stages this dataset or method cannot run fail at job start (`_check_*`)."""
        for stage in stages:
            _check_model_dataset(stage, cfg)
            _check_dataset_stage(stage, cfg)
            _check_held_out_inputs(stage, cfg)
        prepared = Path(cfg.paths.prepared) / PREPROCESS_PROVENANCE
        check_prepared_is_current(stages, prepared, lambda raw: _prepared_key(cfg, raw))

    def render(self, cfg: DictConfig) -> dict:
        """The denoising EXRs into `paths.raw` (files whose render key is unchanged are kept): the
        still-image datasets one EXR per (scene, spp), `dataset=volumetric` one per (scene, frame, spp)."""
        raw = Path(cfg.paths.raw)
        ds = OmegaConf.to_container(cfg.dataset, resolve=True)
        summary_path = Path(cfg.paths.dataset) / "render_summary.json"
        if ds["name"] == "volumetric":
            summary, summary_path = _render_volumetric(ds, raw, cfg.render.variant, summary_path)
        else:
            from src.render.render_dataset import render_denoise_dataset

            summary = render_denoise_dataset(ds, raw, cfg.render.variant)
        if summary["samples_per_second"]:
            print(
                f"render: {summary['files_rendered']} files ({summary['files_cached']} cached) in "
                f"{summary['render_seconds']:.1f} s, {summary['samples_per_second'] / 1e6:.2f} M samples/s "
                f"[{summary['variant']}]"
            )
        else:
            print(f"render: all {summary['files_cached']} files up to date in {raw}")
        write_summary(summary_path, summary, cfg, raw)
        return summary

    def preprocess(self, cfg: DictConfig) -> dict:
        """The raw EXRs into KPCN inputs/targets: patches (train/val) and full images (val/test); for
        `dataset=volumetric`, sequence samples and whole sequences (`_preprocess_volumetric`).

        Skipped when the prepared directory was made from the same settings and raw data (each job of a
        multirun would otherwise redo it)."""
        from src.data.exr_buffers import RepairPolicy
        from src.data.kpcn_buffers import load_kpcn_exr
        from src.data.shards import preprocess_dataset

        if cfg.dataset.name == "volumetric":
            return _preprocess_volumetric(cfg)
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
                patches_per_split=OmegaConf.to_container(p, resolve=True)["patches_per_split"],
                split_fractions=dict(p.split),
                split_seed=p.split_seed,
                sample_seed=p.sample_seed,
                candidates_factor=p.candidates_factor,
                min_keep_prob=p.min_keep_prob,
                min_distance=p.min_distance * p.patch_size,
                whiten_eps=p.whiten_eps,
                importance=p.importance,
                importance_window=p.importance_window,
                importance_percentile=p.importance_percentile,
                specular_variance=p.specular_variance,
                load_fn=load,
            )
            summary["repairs"] = repairs
            write_summary(tmp / PREPROCESS_PROVENANCE, summary, cfg, raw, cache_key=key)
        repaired = f", repaired {len(repairs)} files" if repairs else ""
        print(
            f"preprocess: {summary['noisy_images']} images, {summary['patches']} patches{repaired} -> {out}"
        )
        return summary

    def train(self, cfg: DictConfig, tracker) -> dict:
        """Fit the denoiser: on still-image patches, or (`dataset=volumetric`) on k-frame samples with the
        temporal loss (`src.train.sequence_trainer`)."""
        if cfg.dataset.name == "volumetric":
            from src.train.sequence_trainer import train_sequence_denoiser

            return train_sequence_denoiser(cfg, tracker)
        from src.train.trainer import train_denoiser

        return train_denoiser(cfg, tracker)

    def select_features(self, cfg: DictConfig, tracker) -> dict:
        """The feature-selection probe and its greedy forward selection (`src.train.select_features`)."""
        from src.train.select_features import select_features

        return select_features(cfg, tracker)

    def evaluate(self, cfg: DictConfig, tracker) -> dict:
        if cfg.dataset.name == "volumetric":
            from src.eval.sequence_eval import evaluate_sequences

            summary = evaluate_sequences(cfg, tracker)
        else:
            from src.eval.denoise_eval import evaluate_denoiser

            summary = evaluate_denoiser(cfg, tracker)
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
        """For a model of the volumetric frame batches: the `task.volume_features` it reads (the model
        config knows only their channel count)."""
        from src.data.volume_features import VOLUME_CANDIDATE_FEATURES, volume_feature_channels
        from src.models.denoise.summary import is_frame_model

        if not is_frame_model(model):
            return ""
        selected = cfg.task.volume_features
        features = list(VOLUME_CANDIDATE_FEATURES) if selected is None else [str(f) for f in selected]
        channels = len(volume_feature_channels(features))
        return f"input features (task.volume_features, {channels} channels): {', '.join(features)}"
