"""Still images (`dataset=procedural`): Mitsuba renders of surfaces, one EXR per (scene, spp) in the KPCN /
Tungsten layout, prepared into diffuse/specular network inputs (Bako et al. 2017; the Zagreb thesis,
Bunjevac 2019, Sec. 4), training patches and whole held-out images. The same files from elsewhere (the
KPCN data a user already has) are read with `paths.raw=<folder>` and need no render."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from src.data.features import CANDIDATE_CHANNELS
from src.errors import ConfigError
from src.kinds.denoising import DenoisingKind, cache_key, held_out_index, repaired_note
from src.schema.dataset import ProceduralDataset

#: `task.preprocess` keys only the sequences read (`src.kinds.sequences`): changing them leaves prepared
#: still images valid.
SEQUENCE_ONLY_KEYS = ("volume_transform", "sequence_frames", "patches_per_sequence")


def preprocess_key(cfg: DictConfig, raw: Path) -> str:
    """The still images' cache key: every `task.preprocess` setting but the sequences' own, the stored
    KPCN inputs and the other stored tensors (`SHARD_CHANNEL_NAMES`: folders made before the GP features
    were added rebuild)."""
    settings = OmegaConf.to_container(cfg.task.preprocess, resolve=True)
    settings = {k: v for k, v in settings.items() if k not in SEQUENCE_ONLY_KEYS}
    from src.data.shards import SHARD_CHANNEL_NAMES  # lazy: torch

    return cache_key(settings, raw, (*CANDIDATE_CHANNELS, *SHARD_CHANNEL_NAMES))


class RenderedStills(DenoisingKind):
    """The procedural surface scenes (and user scene files) rendered by `src.render.render_dataset`."""

    schema = ProceduralDataset
    describes = "still images"

    def render_files(self, cfg: DictConfig, raw: Path) -> tuple[dict[str, Any], Path]:
        from src.render.render_dataset import render_denoise_dataset

        ds = OmegaConf.to_container(cfg.dataset, resolve=True)
        summary = render_denoise_dataset(ds, raw, cfg.render.variant)
        return summary, Path(cfg.paths.dataset) / "render_summary.json"

    def check_stage(self, stage: str, cfg: DictConfig) -> None:
        """Feature selection chooses among the sequences' candidates; a model of the sequences' frame
        batches (its builder's `frame_batch`) cannot read diffuse/specular batches; an evaluation whose
        prepared images exist checks now that they hold every buffer the method reads."""
        if stage == "select_features":
            raise ConfigError(
                f"stage=select_features: the feature selection chooses among the volumetric candidates "
                f"(task.volume_features); dataset={cfg.dataset.name} has a fixed feature list "
                "(task.features); run it with dataset=volumetric"
            )
        if stage in ("train", "eval"):
            from src.models.instantiate import resolve_target

            if getattr(resolve_target(cfg.model), "frame_batch", False):
                raise ConfigError(
                    f"model={cfg.model.name} reads the volumetric frame batches: stage={stage} needs "
                    f"dataset=volumetric, not dataset={cfg.dataset.name}"
                )
        if stage == "eval" and held_out_index(cfg).is_file():
            self._check_held_out_inputs(cfg)

    @staticmethod
    def _check_held_out_inputs(cfg: DictConfig) -> None:
        """The one-line error of a method that needs a buffer the prepared images lack (e.g. a GP filter's
        world position on real KPCN data), before any run is opened or file written. (When an earlier
        stage of the job makes them, the eval stage checks the same when it opens them.)"""
        from src.eval.denoise_eval import held_out_images
        from src.models.instantiate import build_method

        held_out_images(cfg, build_method(OmegaConf.to_container(cfg.model, resolve=True)))

    def preprocess(self, cfg: DictConfig) -> dict[str, Any]:
        """The raw EXRs into KPCN inputs/targets: patches (train/val) and full images (val/test); skipped
        when the prepared folder was made from the same settings and raw data (each job of a multirun
        would otherwise redo it)."""
        from src.data.kpcn_buffers import load_kpcn_exr
        from src.data.shards import preprocess_dataset

        p = cfg.task.preprocess
        out = Path(cfg.paths.prepared)

        def build(raw: Path, tmp: Path, load) -> dict[str, Any]:
            return preprocess_dataset(
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

        summary, made = self.prepare(cfg, preprocess_key(cfg, self.raw_dir(cfg)), load_kpcn_exr, build)
        if made:
            print(
                f"preprocess: {summary['noisy_images']} images, {summary['patches']} patches"
                f"{repaired_note(summary)} -> {out}"
            )
        return summary

    def train(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        """Fit the denoiser on the still-image patches (`src.train.trainer`)."""
        from src.train.trainer import train_denoiser

        return train_denoiser(cfg, tracker)

    def evaluate(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        """Score the method on the held-out images (`src.eval.denoise_eval`)."""
        from src.eval.denoise_eval import evaluate_denoiser

        return evaluate_denoiser(cfg, tracker)
