"""What the denoising kinds share: the raw EXRs in `paths.raw`, the prepared folder in `paths.prepared`
(training patches or samples under `patches/`, whole held-out images under `full/<split>/`), and the cache
that keeps a multirun's jobs from preparing the same data again."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

from src.data.prepared_check import check_prepared_is_current, reads_prepared_only
from src.errors import ConfigError
from src.io.atomic import atomic_directory
from src.kinds.base import DataKind
from src.provenance import data_fingerprint, write_summary

PREPROCESS_PROVENANCE = "preprocess_provenance.json"


def cache_key(settings: dict, raw: Path, stored: Sequence[str]) -> str:
    """What prepared data depend on: the preprocessing settings, the raw data's fingerprint and the
    stored channels (prepared folders of an older channel set are made again)."""
    text = json.dumps(settings, sort_keys=True)
    return hashlib.sha256(f"{text}|{data_fingerprint(raw)}|{','.join(stored)}".encode()).hexdigest()[:16]


def cached_preprocess(out: Path, key: str) -> dict | None:
    """The summary of the prepared folder `out` when it was made with `key`, else None."""
    try:
        record = json.loads((out / PREPROCESS_PROVENANCE).read_text())
    except (OSError, ValueError):
        return None
    return record["summary"] if record.get("cache_key") == key else None


def model_branches(model: DictConfig) -> list[str]:
    """The branches a configured model reads: its `branches` key, or its class's declared `branches`."""
    if model.get("branches") is not None:
        return [str(b) for b in model.branches]
    from src.models.instantiate import resolve_target  # lazy: hydra

    return list(getattr(resolve_target(model), "branches", ()))


def held_out_index(cfg: DictConfig) -> Path:
    """The index of the prepared full images that `stage=eval` reads (`task.eval.split`)."""
    return Path(cfg.paths.prepared) / "full" / str(cfg.task.eval.split) / "index.json"


def repaired_note(summary: dict[str, Any]) -> str:
    """The printed line's note of the files repaired on loading (empty when none)."""
    return f", repaired {len(summary['repairs'])} files" if summary["repairs"] else ""


def print_ladder(ladder: Mapping[str, Any], where: str, made: str = "rendered") -> None:
    """The render stage's line about the held-out scenes' ladder (`src.render.ladder_render`'s summary), or
    nothing when no scene has one; `made`: how its files were made."""
    if ladder.get("scenes"):
        print(
            f"render: ladder of {len(ladder['scenes'])} held-out scenes at {ladder['counts']} spp: "
            f"{ladder['files_rendered']} files {made} ({ladder['files_cached']} cached"
            f"{_restored_note(ladder)}) -> {where}"
        )


def _restored_note(summary: Mapping[str, Any]) -> str:
    """The printed line's note of the cached files moved back from `.parked/` (empty when none), where
    another config's render had set them aside (`src.render.stale_renders`)."""
    restored = summary.get("files_restored") or 0
    return f", {restored} of them moved back from .parked/" if restored else ""


class DenoisingKind(DataKind):
    """Noisy renders with their references and auxiliary buffers, prepared for the denoisers. A kind of
    this family also implements `preprocess` and answers what the one trainer (`src/train/trainer.py`) and
    the one evaluation (`src/eval/denoise_eval.py`) ask of the data; the task hands it to them."""

    describes = "denoising data (noisy and reference renders with their buffers)"

    def check_stage(self, stage: str, cfg: DictConfig) -> None:
        """A model that reads a branch these data lack (`model.branches`, or its class's `branches`: the
        U-Net KPCN reads the sequences' `radiance`) cannot train or be evaluated on them; an evaluation
        whose prepared items exist checks now that they hold every buffer the method reads."""
        if stage not in ("train", "eval", "select_features"):
            return
        have = [str(b) for b in self.dataset["branches"]]
        missing = [b for b in model_branches(cfg.model) if b not in have]
        if missing:
            raise ConfigError(
                f"model={cfg.model.name} reads the {', '.join(missing)} branch: stage={stage} needs data "
                f"with it; dataset={self.name} has the {', '.join(have)} branches"
            )
        if stage == "eval" and held_out_index(cfg).is_file():
            self._check_held_out_inputs(cfg)

    def check_stages(self, stages: list[str], cfg: DictConfig) -> None:
        """Besides each stage's checks: a job that reads the prepared folder without preprocessing first
        refuses one made with other settings or raw data (`src.data.prepared_check`)."""
        super().check_stages(stages, cfg)
        if reads_prepared_only(stages):
            record = Path(cfg.paths.prepared) / PREPROCESS_PROVENANCE
            check_prepared_is_current(record, lambda raw: self.preprocess_key(cfg, raw), self.raw_dir(cfg))

    def preprocess_options(self, cfg: DictConfig) -> dict[str, Any]:
        """The preprocessing settings as one mapping: the shared `task.preprocess` and this kind's own
        `dataset.preprocess` (none for a kind without it). One mapping, as when they all lived in
        `task.preprocess`: the prepared folders' cache keys did not change when they moved."""
        shared = OmegaConf.to_container(cfg.task.preprocess, resolve=True)
        return {**shared, **self.dataset.get("preprocess", {})}

    def scene_splits(self, cfg: DictConfig) -> dict[str, list[str]]:
        """The train/val/test scenes preprocessing will make of this config's renders: `split_scenes` of
        every scene the dataset renders, with the `task.preprocess` split settings preprocessing uses."""
        from src.data.splits import split_scenes

        p = self.preprocess_options(cfg)
        split_by_base = bool(p.get("split_by_base", False))
        return split_scenes(self.scene_names(), p["split"], p["split_seed"], split_by_base)

    def scene_names(self) -> list[str]:
        """The names of every scene (or sequence) this dataset renders, as its raw files name them."""
        from src.render.render_dataset import scene_sources  # lazy: the render package

        return [source.name for source in scene_sources(self.dataset)]

    def ladder_scenes(self, cfg: DictConfig) -> list[str]:
        """The scenes whose sample-count ladder the render stage makes (`src.data.ladder`): those of
        `task.eval.split`, the ones the evaluation scores; none when `dataset.ladder_spp` is empty."""
        if not self.dataset.get("ladder_spp"):
            return []
        return self.scene_splits(cfg)[str(cfg.task.eval.split)]

    def preprocess_key(self, cfg: DictConfig, raw: Path) -> str:
        """The cache key `preprocess` gives the prepared folder for this config and the raw data `raw`."""
        raise NotImplementedError

    def _check_held_out_inputs(self, cfg: DictConfig) -> None:
        """The one-line error of a method that needs a buffer the prepared items lack (e.g. a GP filter's
        world position on real KPCN data, or its variance guides on sequences), before any run is opened
        or file written. (When an earlier stage of the job makes them, the eval stage checks the same when
        it opens them.)"""
        from src.models.instantiate import build_method

        self.held_out(cfg, self.features(cfg), build_method(OmegaConf.to_container(cfg.model, resolve=True)))

    def raw_dir(self, cfg: DictConfig) -> Path:
        """Where the raw EXRs are (`paths.raw`)."""
        return Path(cfg.paths.raw)

    def data_dir(self, cfg: DictConfig) -> Path:
        """The data the runs' `nrbench.data_fingerprint` tag identifies: the raw EXRs."""
        return self.raw_dir(cfg)

    def inputs(self, stage: str, cfg: DictConfig) -> dict[Path, str]:
        prepared, preprocessed = Path(cfg.paths.prepared), "stage=preprocess (or dvc repro)"
        if stage == "preprocess":
            return {self.raw_dir(cfg): "stage=render (or dvc repro)"}
        if stage in ("train", "select_features"):
            return {prepared / "patches" / "train" / "index.json": preprocessed}
        if stage == "eval":
            return {held_out_index(cfg): preprocessed}
        return {}

    def render(self, cfg: DictConfig) -> dict[str, Any]:
        """The EXRs into `paths.raw` (files whose render key is unchanged are kept), with a summary file."""
        raw = self.raw_dir(cfg)
        summary, summary_path = self.render_files(cfg, raw)
        if summary["samples_per_second"]:
            print(
                f"render: {summary['files_rendered']} files ({summary['files_cached']} cached"
                f"{_restored_note(summary)}) in {summary['render_seconds']:.1f} s, "
                f"{summary['samples_per_second'] / 1e6:.2f} M samples/s [{summary['variant']}]"
            )
        else:
            print(f"render: all {summary['files_cached']} files up to date in {raw}{_restored_note(summary)}")
        print_ladder(summary.get("ladder") or {}, cfg.paths.ladder)
        write_summary(summary_path, summary, cfg, raw)
        return summary

    def render_files(self, cfg: DictConfig, raw: Path) -> tuple[dict[str, Any], Path]:
        """Render into `raw`; returns the render summary and the file to write it to."""
        raise NotImplementedError

    def preprocess(self, cfg: DictConfig) -> dict[str, Any]:
        """The raw EXRs into what training and evaluation read (`paths.prepared`)."""
        raise NotImplementedError

    def prepare(
        self, cfg: DictConfig, key: str, load_exr: Callable, build: Callable[[Path, Path, Callable], dict]
    ) -> tuple[dict[str, Any], bool]:
        """(summary, made): the prepared folder's summary when it was made with cache key `key` (made False:
        each job of a multirun would otherwise redo it), else `build(raw, folder, load)`'s, made in a
        temporary folder renamed into place (a crash leaves nothing a later stage trusts). `load` is
        `load_exr` (a layout's loader) with `task.preprocess.repair`; the repairs it made, per file, are
        in the summary and its provenance file."""
        raw, out = self.raw_dir(cfg), Path(cfg.paths.prepared)
        cached = cached_preprocess(out, key)
        if cached is not None:
            print(f"preprocess: up to date in {out}")
            return cached, False
        from src.data.exr_buffers import RepairPolicy

        policy = RepairPolicy(**OmegaConf.to_container(cfg.task.preprocess.repair, resolve=True))
        repairs: dict[str, str] = {}

        def load(path: Path, buffers=None):
            loaded, report = load_exr(path, repair=policy, buffers=buffers)
            if report.total:
                # by path within the raw folder: a second reference (reference2/) has its reference's name
                repairs[str(path.relative_to(raw)) if path.is_relative_to(raw) else path.name] = (
                    report.summary()
                )
            return loaded

        with atomic_directory(out) as tmp:
            summary = build(raw, tmp, load)
            summary["repairs"] = repairs
            write_summary(tmp / PREPROCESS_PROVENANCE, summary, cfg, raw, cache_key=key)
        return summary, True

    # -- what the one denoising trainer and evaluation ask of the data, which the task hands them
    # (src/train/trainer.py, src/eval/denoise_eval.py) ---------------------------------------------------
    #: Progress-bar units of a training sample and of a held-out item; whether items are sequences (their
    #: rows then carry a frame count and the flicker metric); the input group the feature-selection probe
    #: drops features of (None: no probe on these data).
    sample_unit = "sample"
    eval_unit = "img"
    temporal = False
    probe_key: str | None = None

    def features(self, cfg: DictConfig) -> list[str] | None:
        """The run's input features, by name (what a checkpoint records)."""
        raise NotImplementedError

    def check_trained_features(
        self, checkpoint: dict[str, Any], features: list[str] | None, where: str
    ) -> None:
        """A one-line DataError when the checkpoint's model was trained on other features."""
        raise NotImplementedError

    def color_space(self, cfg: DictConfig):
        """How branch outputs become linear colour (`src.data.color_spaces`)."""
        raise NotImplementedError

    def training_data(self, cfg: DictConfig, features: list[str] | None) -> tuple[Any, Any]:
        """The training (shuffled per epoch) and validation datasets: items of k frames."""
        return (
            self.samples(cfg, "train", features, shuffle=True),
            self.samples(cfg, "val", features, shuffle=False),
        )

    def samples(self, cfg: DictConfig, split: str, features: list[str] | None, shuffle: bool):
        """The prepared training samples of `split` (`training_data`), seeded by `seed`."""
        raise NotImplementedError

    def build_context(self, cfg: DictConfig, train_data) -> dict[str, Any]:
        """What the model's builder gets besides its config (default: nothing)."""
        return {}

    def schedule(self, cfg: DictConfig):
        """The learning-rate schedule's config (`task.train.schedule`; None: constant)."""
        return cfg.task.train.get("schedule")

    def loss_terms(self, cfg: DictConfig, train_data):
        """What the model is fitted to (`src.objectives.terms`)."""
        raise NotImplementedError

    def held_out(self, cfg: DictConfig, features: list[str] | None, model):
        """The held-out items of `task.eval.split`: (F, C, H, W) tensors and `scene`, `spp`,
        `reference_spp`; checked against what `model` reads where the data allow it before any frame."""
        raise NotImplementedError

    def training_summary(self, model, cfg: DictConfig) -> str:
        """Lines `stage=summary` adds about the inputs a model reads on this data (default: none)."""
        return ""
