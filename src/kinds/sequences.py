"""Sequences (`dataset=volumetric`): Mitsuba renders of animated heterogeneous media, one EXR per (scene,
frame, spp) with the volumetric path tracer's buffers, prepared into k-frame training samples and whole
held-out sequences; trained with the temporal loss and scored per frame and for flicker (after Zhu et
al.'s 2023 Pixar/Disney talk "Denoising Production Volumetric Rendering"). Its inputs are chosen by name
from a catalogue of candidates (`task.volume_features`), possibly by the feature-selection stage."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from src.data.sequence_patches import FRAMES_KEY
from src.errors import ConfigError
from src.kinds.denoising import DenoisingKind, cache_key, repaired_note
from src.schema.dataset import VolumetricDataset


def preprocess_settings(cfg: DictConfig) -> dict[str, Any]:
    """The keyword arguments of `preprocess_volume_dataset` from `task.preprocess`."""
    p = OmegaConf.to_container(cfg.task.preprocess, resolve=True)
    return {
        **{k: p[k] for k in ("patch_size", "patches_per_sequence", "sequence_frames", "volume_transform")},
        "split_fractions": p["split"],
        **{k: p[k] for k in ("split_seed", "sample_seed", "candidates_factor", "min_keep_prob")},
        "min_distance": p["min_distance"] * p["patch_size"],
        **{k: p[k] for k in ("importance", "importance_window", "importance_percentile", "whiten_eps")},
    }


class RenderedSequences(DenoisingKind):
    """The procedural volumetric scene family rendered by `src.render.volume_dataset`."""

    schema = VolumetricDataset
    describes = "image sequences"

    def render_files(self, cfg: DictConfig, raw: Path) -> tuple[dict[str, Any], Path]:
        """Every sequence, or the `render_scenes` / `render_frames` subset a fanned-out job was given: then
        one summary file per subset, so jobs keep theirs."""
        from src.render.volume_dataset import render_volumetric_dataset

        ds = OmegaConf.to_container(cfg.dataset, resolve=True)
        scenes, frames = ds.get("render_scenes"), ds.get("render_frames")
        summary = render_volumetric_dataset(ds, raw, cfg.render.variant, scenes=scenes, frames=frames)
        summary_path = Path(cfg.paths.dataset) / "render_summary.json"
        if scenes is not None or frames is not None:
            tag = hashlib.sha256(json.dumps([scenes, frames]).encode()).hexdigest()[:8]
            summary_path = summary_path.with_name(f"render_summary-{tag}.json")
        return summary, summary_path

    def check_stage(self, stage: str, cfg: DictConfig) -> None:
        """A preprocessing window longer than the sequences is one line."""
        k, frames = cfg.task.preprocess.sequence_frames, cfg.dataset.frames
        if stage == "preprocess" and k > frames:
            raise ConfigError(
                f"{FRAMES_KEY}={k} is more than the dataset.frames={frames} frames of each volumetric "
                "sequence"
            )

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

    def preprocess(self, cfg: DictConfig) -> dict[str, Any]:
        """The sequences into k-frame samples (train/val) and whole sequences (val/test)
        (`src.data.volume_shards`); skipped when made from the same settings, repair policy and raw data."""
        from src.data.volume_buffers import load_volume_exr
        from src.data.volume_features import VOLUME_CANDIDATE_CHANNELS
        from src.data.volume_shards import SEQUENCE_KEYS, preprocess_volume_dataset

        repair = OmegaConf.to_container(cfg.task.preprocess.repair, resolve=True)
        settings = preprocess_settings(cfg)
        stored = (*SEQUENCE_KEYS, *VOLUME_CANDIDATE_CHANNELS)
        key = cache_key({**settings, "repair": repair}, self.raw_dir(cfg), stored)

        def build(raw: Path, tmp: Path, load) -> dict[str, Any]:
            return preprocess_volume_dataset(raw, tmp, **settings, load_fn=load)

        summary, made = self.prepare(cfg, key, load_volume_exr, build)
        if made:
            samples, full = summary["samples"], summary["full_sequences"]
            print(
                f"preprocess: {summary['noisy_sequences']} noisy sequences: {samples['train']} train / "
                f"{samples['val']} val samples of {settings['sequence_frames']} frames, {full['val']} val / "
                f"{full['test']} test whole sequences{repaired_note(summary)} in {summary['seconds']:.1f} s "
                f"-> {cfg.paths.prepared}"
            )
        return summary

    def train(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        """Fit the denoiser on k-frame samples with the temporal loss (`src.train.sequence_trainer`)."""
        from src.train.sequence_trainer import train_sequence_denoiser

        return train_sequence_denoiser(cfg, tracker)

    def evaluate(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        """Score the method per frame and for flicker on the held-out sequences (`src.eval.sequence_eval`)."""
        from src.eval.sequence_eval import evaluate_sequences

        return evaluate_sequences(cfg, tracker)

    def training_summary(self, model, cfg: DictConfig) -> str:
        """For a model of the frame batches: the `task.volume_features` it reads (the model config knows
        only their channel count)."""
        from src.data.volume_features import VOLUME_CANDIDATE_FEATURES, volume_feature_channels
        from src.models.denoise.summary import is_frame_model

        if not is_frame_model(model):
            return ""
        selected = cfg.task.volume_features
        features = list(VOLUME_CANDIDATE_FEATURES) if selected is None else [str(f) for f in selected]
        channels = len(volume_feature_channels(features))
        return f"input features (task.volume_features, {channels} channels): {', '.join(features)}"
