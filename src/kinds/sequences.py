"""Sequences (`dataset=volumetric`): Mitsuba renders of animated heterogeneous media, one EXR per (scene,
frame, spp) with the volumetric path tracer's buffers, prepared into k-frame training samples and whole
held-out sequences; trained with the temporal loss and scored per frame and for flicker (after Zhu et
al.'s 2023 Pixar/Disney talk "Denoising Production Volumetric Rendering"). Its inputs are chosen by name
from a catalogue of candidates (`dataset.volume_features`), possibly by the feature-selection stage.

Its own options (conf/dataset/sequences/options.yaml, part of `dataset:` and so of its constructor's
arguments, `self.dataset`): the input features and their selection, the sequences' preprocessing
(`dataset.preprocess`: transform, frames per sample, samples per sequence) and what a model is fitted to
(`dataset.train`: reconstruction loss, temporal term, schedule). What every denoising kind shares (patch
size, sampling, split, seeds, repair policy; the training budget and optimiser) is read from `task:`."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from src.data.color_spaces import RadianceTransform
from src.data.sequence_dataset import RADIANCE_BRANCH
from src.data.sequence_patches import FRAMES_KEY
from src.errors import ConfigError, DataError
from src.kinds.denoising import DenoisingKind, cache_key, repaired_note
from src.objectives.losses import get_loss
from src.objectives.terms import TemporalLosses
from src.schema.dataset import VolumetricDataset


class RenderedSequences(DenoisingKind):
    """The procedural volumetric scene family rendered by `src.render.volume_dataset`."""

    schema = VolumetricDataset
    describes = "image sequences"

    def preprocess_settings(self, cfg: DictConfig) -> dict[str, Any]:
        """The keyword arguments of `preprocess_volume_dataset`: the shared `task.preprocess` and the
        sequences' own `dataset.preprocess`."""
        p = self.preprocess_options(cfg)
        return {
            **{
                k: p[k] for k in ("patch_size", "patches_per_sequence", "sequence_frames", "volume_transform")
            },
            "split_fractions": p["split"],
            **{k: p[k] for k in ("split_seed", "sample_seed", "candidates_factor", "min_keep_prob")},
            "min_distance": p["min_distance"] * p["patch_size"],
            **{k: p[k] for k in ("importance", "importance_window", "importance_percentile", "whiten_eps")},
            # only when on: the cache keys of folders made before the option stay the same
            **({"split_by_base": True} if p.get("split_by_base") else {}),
            # the held-out sequences' second reference (dataset.second_reference; absent when off, as above)
            **({"second_reference": True} if self.dataset.get("second_reference") else {}),
        }

    def held_out_scenes(self, cfg: DictConfig) -> list[str]:
        """The val and test scenes preprocessing will make of this config's renders (`scene_splits`, with
        the keys `preprocess_volume_dataset` reads); the scenes whose second reference the render stage
        makes."""
        splits = self.scene_splits(cfg)
        return sorted(splits["val"] + splits["test"])

    def export_noisebase(self, cfg: DictConfig) -> list[Path]:
        """Every frame of the `export.scenes` animations, `export.spp` 1-spp passes each."""
        from src.render.noisebase_export import export_volumetric_sequences

        e, ds = cfg.export, self.dataset
        scenes = list(e.scenes) if e.scenes is not None else None
        return export_volumetric_sequences(ds, Path(e.out_dir), e.format, e.spp, scenes, cfg.render.variant)

    def render_files(self, cfg: DictConfig, raw: Path) -> tuple[dict[str, Any], Path]:
        """Every sequence, or the `render_scenes` / `render_frames` subset a fanned-out job was given: then
        one summary file per subset, so jobs keep theirs. With `dataset.second_reference`, also the second
        reference of the held-out scenes (`held_out_scenes`); with `dataset.ladder_spp`, the ladder of plain
        renders of the scenes `task.eval.split` holds out (`ladder_scenes`; `src.data.ladder`)."""
        from src.render.ladder_render import render_sequence_ladder
        from src.render.volume_dataset import render_volumetric_dataset

        ds = self.dataset
        scenes, frames = ds.get("render_scenes"), ds.get("render_frames")
        second = self.held_out_scenes(cfg) if ds.get("second_reference") else []
        summary = render_volumetric_dataset(
            ds, raw, cfg.render.variant, scenes=scenes, frames=frames, second_reference=second
        )
        ladder = [s for s in self.ladder_scenes(cfg) if scenes is None or s in scenes]
        summary["ladder"] = render_sequence_ladder(
            ds, Path(cfg.paths.ladder), ladder, summary["frames"], cfg.render.variant
        )
        summary_path = Path(cfg.paths.dataset) / "render_summary.json"
        if scenes is not None or frames is not None:
            tag = hashlib.sha256(json.dumps([scenes, frames]).encode()).hexdigest()[:8]
            summary_path = summary_path.with_name(f"render_summary-{tag}.json")
        return summary, summary_path

    def check_stage(self, stage: str, cfg: DictConfig) -> None:
        """Besides the branch check: a preprocessing window longer than the sequences, and input
        whitening (no whitening statistics of the sequences' inputs are passed to a model), are one line."""
        super().check_stage(stage, cfg)
        k, frames = self.dataset["preprocess"]["sequence_frames"], self.dataset["frames"]
        if stage == "preprocess" and k > frames:
            raise ConfigError(
                f"{FRAMES_KEY}={k} is more than the dataset.frames={frames} frames of each volumetric "
                "sequence"
            )
        if stage in ("train", "eval", "select_features") and cfg.model.get("whiten"):
            raise ConfigError(
                "model.whiten: true is not supported on dataset=volumetric (no whitening statistics of the "
                "sequences' inputs); set model.whiten=false"
            )

    def resolve_at_job_start(self, cfg: DictConfig) -> None:
        """`dataset.feature_selection.size` = k: `dataset.volume_features` becomes the start set plus the
        first k features of the selection stage's output (or k drawn at random), so the model's `in_channels`
        follows; null leaves the configured features. The chosen names get the schema's check (it ran
        before they were known): a hand-edited selection file is one line, not a failure later. Both the
        config (which the model's `in_channels` interpolates) and this kind's options get them."""
        selection = OmegaConf.create(self.dataset["feature_selection"])
        if selection.size is not None:
            from src.data.feature_choice import features_for_size
            from src.data.volume_features import volume_feature_channels

            features = features_for_size(selection)
            volume_feature_channels(features)
            cfg.dataset.volume_features = features
            self.dataset["volume_features"] = features

    def preprocess_key(self, cfg: DictConfig, raw: Path) -> str:
        """The settings, the repair policy, the raw data and the stored channels."""
        from src.data.volume_features import VOLUME_CANDIDATE_CHANNELS
        from src.data.volume_shards import SEQUENCE_KEYS

        repair = OmegaConf.to_container(cfg.task.preprocess.repair, resolve=True)
        settings = {**self.preprocess_settings(cfg), "repair": repair}
        return cache_key(settings, raw, (*SEQUENCE_KEYS, *VOLUME_CANDIDATE_CHANNELS))

    def preprocess(self, cfg: DictConfig) -> dict[str, Any]:
        """The sequences into k-frame samples (train/val) and whole sequences (val/test)
        (`src.data.volume_shards`); skipped when made from the same settings, repair policy and raw data."""
        from src.data.volume_buffers import load_volume_exr
        from src.data.volume_shards import preprocess_volume_dataset

        settings = self.preprocess_settings(cfg)
        key = self.preprocess_key(cfg, self.raw_dir(cfg))

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

    # -- what the denoising trainer and evaluation read ----------------------------------------------------
    eval_unit = "seq"
    temporal = True
    probe_key = f"{RADIANCE_BRANCH}_in"

    def features(self, cfg: DictConfig) -> list[str] | None:
        features = self.dataset["volume_features"]
        return None if features is None else [str(f) for f in features]

    def check_trained_features(self, checkpoint: dict[str, Any], features, where: str) -> None:
        trained = checkpoint.get("features", features)
        if trained != features:
            raise DataError(
                f"{where}: trained with dataset.volume_features={trained} (null: all), configured "
                f"{features}; evaluate with the features it was trained on"
            )

    def color_space(self, cfg: DictConfig) -> RadianceTransform:
        return RadianceTransform(self.dataset["preprocess"]["volume_transform"])

    def samples(self, cfg: DictConfig, split: str, features, shuffle: bool):
        """k-frame samples of `split` (`SequencePatchDataset`)."""
        from src.data.sequence_dataset import SequencePatchDataset

        return SequencePatchDataset(
            cfg.paths.prepared, split, seed=int(cfg.seed), shuffle=shuffle, features=features
        )

    def schedule(self, cfg: DictConfig):
        """`dataset.train.schedule` (the talk's decay), else `task.train.schedule`."""
        own = self.dataset["train"].get("schedule")
        return own if own is not None else super().schedule(cfg)

    def loss_terms(self, cfg: DictConfig, train_data) -> TemporalLosses:
        """Reconstruction + temporal loss (`dataset.train`), in the prepared data's transform."""
        v = self.dataset["train"]
        return TemporalLosses(
            get_loss(v["loss"]),
            self.color_space(cfg),
            weight=v["temporal_weight"],
            mode=v["temporal_mode"],
            warp=v["temporal_warp"],
            transform=train_data.volume_transform,
        )

    def held_out(self, cfg: DictConfig, features, model):
        """The whole sequences of `task.eval.split`, after checking from their index that they hold what
        `model` reads (`Denoiser.check_batch_keys`)."""
        from src.data.sequence_dataset import SequenceDataset

        data = SequenceDataset(cfg.paths.prepared, cfg.task.eval.split, features=features)
        model.check_batch_keys(data.batch_keys)
        return data

    def training_summary(self, model, cfg: DictConfig) -> str:
        """For a model of the radiance branch: the `dataset.volume_features` it reads (the model config knows
        only their channel count)."""
        from src.data.volume_features import VOLUME_CANDIDATE_FEATURES, volume_feature_channels

        if RADIANCE_BRANCH not in getattr(model, "branches", ()):
            return ""
        selected = self.features(cfg)
        features = list(VOLUME_CANDIDATE_FEATURES) if selected is None else selected
        channels = len(volume_feature_channels(features))
        return f"input features (dataset.volume_features, {channels} channels): {', '.join(features)}"
