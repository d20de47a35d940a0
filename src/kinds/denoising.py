"""What the denoising kinds share: the raw EXRs in `paths.raw`, the prepared folder in `paths.prepared`
(training patches or samples under `patches/`, whole held-out images under `full/<split>/`), and the cache
that keeps a multirun's jobs from preparing the same data again."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from omegaconf import DictConfig, OmegaConf

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


def held_out_index(cfg: DictConfig) -> Path:
    """The index of the prepared full images that `stage=eval` reads (`task.eval.split`)."""
    return Path(cfg.paths.prepared) / "full" / str(cfg.task.eval.split) / "index.json"


class DenoisingKind(DataKind):
    """Noisy renders with their references and auxiliary buffers, prepared for the denoisers. A kind of
    this family also implements `preprocess`, `train` and `evaluate` (the summaries the task prints)."""

    describes = "denoising data (noisy and reference renders with their buffers)"

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
                f"render: {summary['files_rendered']} files ({summary['files_cached']} cached) in "
                f"{summary['render_seconds']:.1f} s, {summary['samples_per_second'] / 1e6:.2f} M samples/s "
                f"[{summary['variant']}]"
            )
        else:
            print(f"render: all {summary['files_cached']} files up to date in {raw}")
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
                repairs[path.name] = report.summary()
            return loaded

        with atomic_directory(out) as tmp:
            summary = build(raw, tmp, load)
            summary["repairs"] = repairs
            write_summary(tmp / PREPROCESS_PROVENANCE, summary, cfg, raw, cache_key=key)
        return summary, True


def repaired_note(summary: dict[str, Any]) -> str:
    """The printed line's note of the files repaired on loading (empty when none)."""
    return f", repaired {len(summary['repairs'])} files" if summary["repairs"] else ""

    def train(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        raise NotImplementedError

    def evaluate(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        raise NotImplementedError

    def training_summary(self, model, cfg: DictConfig) -> str:
        """Lines `stage=summary` adds about the inputs a model reads on this data (default: none)."""
        return ""
