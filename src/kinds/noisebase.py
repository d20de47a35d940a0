"""Noisebase sample sets (`dataset=noisebase`, issue 35): the per-sample training and test sequences of
Balint et al. 2023 ("Neural Partitioning Pyramids for Denoising Monte Carlo Renderings"), read from a
downloaded folder (`dataset.root`) into the volumetric sequences' raw layout, after which they are
prepared, trained on and scored exactly as `dataset=volumetric` (`src.kinds.sequences`): k-frame samples
for the sequence models, whole held-out sequences for evaluation. The reading: `src.data.noisebase`
(docs/noisebase.md)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from src.kinds.base import DataKind
from src.kinds.denoising import print_ladder
from src.kinds.sequences import RenderedSequences
from src.provenance import write_summary
from src.schema.dataset import NoisebaseDataset


class NoisebaseSequences(RenderedSequences):
    """Noisebase sequences as nrbench sequences: `stage=render` converts the configured sequences, frames,
    window and sample counts (nothing is rendered); the rest is the volumetric kind's."""

    schema = NoisebaseDataset
    describes = "image sequences (Noisebase sample sets)"
    export_noisebase = DataKind.export_noisebase  # it reads sets and renders none: refused in one line

    def scene_names(self) -> list[str]:
        """The configured sequences' names (`scene0000`, ... or the test set's names)."""
        from src.data.noisebase import sequence_sources

        return list(sequence_sources(self.dataset))

    def render(self, cfg: DictConfig) -> dict[str, Any]:
        """The configured sequences of the set at `dataset.root` into `paths.raw`
        (`src.data.noisebase.convert_to_volume_exrs`), with a summary file; with `dataset.ladder_spp`, the
        sample-count ladder of the sequences `task.eval.split` holds out, averaged from their stored samples
        (`src.render.ladder_render.noisebase_ladder`) into `paths.ladder`."""
        from src.data.noisebase import convert_to_volume_exrs
        from src.render.ladder_render import noisebase_ladder

        raw = self.raw_dir(cfg)
        summary = convert_to_volume_exrs(self.dataset, raw)
        if summary["files_written"]:
            print(
                f"render: {summary['files_written']} files from {summary['sequences']} Noisebase sequences "
                f"in {summary['seconds']:.1f} s -> {raw}"
            )
        else:
            print(f"render: all {summary['files_cached']} files up to date in {raw}")
        summary["ladder"] = noisebase_ladder(self.dataset, Path(cfg.paths.ladder), self.ladder_scenes(cfg))
        print_ladder(summary["ladder"], cfg.paths.ladder, made="averaged from their stored samples")
        write_summary(Path(cfg.paths.dataset) / "render_summary.json", summary, cfg, raw)
        return summary
