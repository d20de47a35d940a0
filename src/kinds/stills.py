"""Still images (`dataset=procedural`): Mitsuba renders of surfaces, one EXR per (scene, spp) in the KPCN /
Tungsten layout, prepared into diffuse/specular network inputs (Bako et al. 2017; the Zagreb thesis,
Bunjevac 2019, Sec. 4), training patches and whole held-out images. The same files from elsewhere (the
KPCN data a user already has) are read with `paths.raw=<folder>` and need no render.

Its own options (conf/dataset/procedural.yaml, `self.dataset`): the scenes and their renders, and their
preprocessing `dataset.preprocess` (the KPCN transform's `eps_albedo` and `specular_variance`, the patch
counts). Its input features are `task.features`, which the filter search sets to its own terminals on the
same images."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from src.data.color_spaces import KpcnSplit
from src.data.denoise_dataset import FramesOfOne, ImagesAsFrames
from src.data.features import CANDIDATE_CHANNELS, check_trained_features, input_features
from src.errors import ConfigError
from src.kinds.denoising import DenoisingKind, cache_key, repaired_note
from src.objectives.losses import get_loss
from src.objectives.terms import BranchLosses
from src.schema.dataset import ProceduralDataset


class RenderedStills(DenoisingKind):
    """The procedural surface scenes (and user scene files) rendered by `src.render.render_dataset`."""

    schema = ProceduralDataset
    describes = "still images"

    def export_noisebase(self, cfg: DictConfig) -> list[Path]:
        """The `export.scenes` still scenes as `export.frames`-frame camera pans of `export.pan_deg` per
        frame, `export.spp` 1-spp passes each."""
        from src.render.noisebase_export import export_still_sequences

        e, ds = cfg.export, self.dataset
        scenes = list(e.scenes) if e.scenes is not None else None
        return export_still_sequences(
            ds, Path(e.out_dir), e.format, e.spp, e.frames, e.pan_deg, scenes, cfg.render.variant
        )

    def render_files(self, cfg: DictConfig, raw: Path) -> tuple[dict[str, Any], Path]:
        """Every scene at every count, and the ladder of plain renders of the scenes `task.eval.split`
        holds out (`ladder_scenes`; `src.data.ladder`)."""
        from src.render.ladder_render import render_still_ladder
        from src.render.render_dataset import render_denoise_dataset

        summary = render_denoise_dataset(self.dataset, raw, cfg.render.variant)
        summary["ladder"] = render_still_ladder(
            self.dataset, Path(cfg.paths.ladder), self.ladder_scenes(cfg), cfg.render.variant
        )
        return summary, Path(cfg.paths.dataset) / "render_summary.json"

    def preprocess_key(self, cfg: DictConfig, raw: Path) -> str:
        """The still images' cache key: every setting of the shared `task.preprocess` and of their own
        `dataset.preprocess`, the stored KPCN inputs and the other stored tensors (`SHARD_CHANNEL_NAMES`:
        folders made before the GP features were added rebuild), over `preprocess_options`."""
        settings = self.preprocess_options(cfg)
        if not settings.get("split_by_base"):  # off: the keys of folders made before the option stay the same
            settings.pop("split_by_base", None)
        from src.data.shards import SHARD_CHANNEL_NAMES  # lazy: torch

        return cache_key(settings, raw, (*CANDIDATE_CHANNELS, *SHARD_CHANNEL_NAMES))

    def check_stage(self, stage: str, cfg: DictConfig) -> None:
        """Besides the shared checks: feature selection chooses among the sequences' candidates."""
        super().check_stage(stage, cfg)
        if stage == "select_features":
            raise ConfigError(
                f"stage=select_features: the feature selection chooses among the volumetric candidates "
                f"(dataset.volume_features); dataset={self.name} has a fixed feature list "
                "(task.features); run it with dataset=volumetric"
            )

    def preprocess(self, cfg: DictConfig) -> dict[str, Any]:
        """The raw EXRs into KPCN inputs/targets: patches (train/val) and full images (val/test); skipped
        when the prepared folder was made from the same settings and raw data (each job of a multirun
        would otherwise redo it)."""
        from src.data.kpcn_buffers import load_kpcn_exr
        from src.data.shards import preprocess_dataset

        p, own = cfg.task.preprocess, self.dataset["preprocess"]
        out = Path(cfg.paths.prepared)

        def build(raw: Path, tmp: Path, load) -> dict[str, Any]:
            return preprocess_dataset(
                raw,
                tmp,
                eps=own["eps_albedo"],
                patch_size=p.patch_size,
                patches_per_image=own["patches_per_image"],
                patches_per_split=own["patches_per_split"],
                split_fractions=dict(p.split),
                split_seed=p.split_seed,
                split_by_base=bool(p.split_by_base),
                sample_seed=p.sample_seed,
                candidates_factor=p.candidates_factor,
                min_keep_prob=p.min_keep_prob,
                min_distance=p.min_distance * p.patch_size,
                whiten_eps=p.whiten_eps,
                importance=p.importance,
                importance_window=p.importance_window,
                importance_percentile=p.importance_percentile,
                specular_variance=own["specular_variance"],
                load_fn=load,
            )

        summary, made = self.prepare(cfg, self.preprocess_key(cfg, self.raw_dir(cfg)), load_kpcn_exr, build)
        if made:
            print(
                f"preprocess: {summary['noisy_images']} images, {summary['patches']} patches"
                f"{repaired_note(summary)} -> {out}"
            )
        return summary

    # -- what the denoising trainer and evaluation read ----------------------------------------------------
    sample_unit = "patch"

    def features(self, cfg: DictConfig) -> list[str]:
        return input_features(cfg)

    def check_trained_features(self, checkpoint: dict[str, Any], features, where: str) -> None:
        check_trained_features(checkpoint.get("features"), features, where)

    def color_space(self, cfg: DictConfig) -> KpcnSplit:
        return KpcnSplit(self.dataset["preprocess"]["eps_albedo"])

    def samples(self, cfg: DictConfig, split: str, features, shuffle: bool) -> FramesOfOne:
        """Patches of `split` (`PatchShardDataset`), as samples of one frame."""
        from src.data.denoise_dataset import PatchShardDataset

        data = PatchShardDataset(
            cfg.paths.prepared, split, seed=int(cfg.seed), shuffle=shuffle, features=features
        )
        return FramesOfOne(data)

    def build_context(self, cfg: DictConfig, train_data: FramesOfOne) -> dict[str, Any]:
        """The whitening statistics of the selected inputs, for a model that whitens (an ablation)."""
        if not cfg.model.get("whiten"):
            return {"whitening": None}
        from src.data.denoise_dataset import selected_whitening

        path = Path(cfg.paths.prepared) / "whitening.json"
        return {"whitening": selected_whitening(path, train_data.patches.select)}

    def loss_terms(self, cfg: DictConfig, train_data) -> BranchLosses:
        return BranchLosses(get_loss(cfg.task.train.loss), self.color_space(cfg))

    def held_out(self, cfg: DictConfig, features, model) -> ImagesAsFrames:
        """The full images of `task.eval.split`, after checking from their index that they hold what
        `model` reads (`Denoiser.check_batch_keys`: a one-line error before any image is denoised)."""
        from src.data.denoise_dataset import FullImageDataset

        data = FullImageDataset(cfg.paths.prepared, cfg.task.eval.split, features=features)
        model.check_batch_keys(data.batch_keys)
        return ImagesAsFrames(data)
