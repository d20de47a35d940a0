"""Multi-view scenes for the radiance fields, in the Blender (nerf_synthetic) format:
`<paths.scenes>/<scene>/transforms_{train,val,test}.json` and RGBA PNGs. Rendered by the harness with
Mitsuba (`dataset=nerf_procedural`) or read from a user's folder (`dataset=blender dataset.root=...`)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig

from src.data.blender import scene_dir
from src.kinds.base import DataKind
from src.provenance import write_summary
from src.schema.dataset import BlenderDataset, NerfProceduralDataset


class MultiViewKind(DataKind):
    """Posed views of scenes, one scene per job (`task.scene`)."""

    describes = "multi-view scenes (Blender format)"
    #: What makes the scene folders, for the line of a stage started too early.
    producer = "stage=render (or dvc repro)"

    def inputs(self, stage: str, cfg: DictConfig) -> dict[Path, str]:
        if stage == "train":
            return {scene_dir(cfg) / "transforms_train.json": self.producer}
        if stage == "eval":
            return {scene_dir(cfg) / f"transforms_{cfg.task.eval.split}.json": self.producer}
        return {}

    def data_dir(self, cfg: DictConfig) -> Path:
        """The data the runs' `nrbench.data_fingerprint` tag identifies: this job's scene."""
        return scene_dir(cfg)


class RenderedScenes(MultiViewKind):
    """The procedural scenes rendered by `src.render.multiview` into `paths.scenes`."""

    schema = NerfProceduralDataset
    describes = "rendered multi-view scenes"

    def render(self, cfg: DictConfig) -> dict[str, Any]:
        from src.render.multiview import render_multiview_dataset

        scenes = Path(cfg.paths.scenes)
        summary = render_multiview_dataset(self.dataset, scenes, cfg.render.variant)
        print(
            f"render: {summary.get('scenes_rendered', 0)} scenes rendered, {summary.get('scenes_cached', 0)} "
            f"up to date in {scenes} ({(summary.get('rays_per_second') or 0) / 1e6:.2f} M rays/s)"
        )
        write_summary(Path(cfg.paths.dataset) / "render_summary.json", summary, cfg, scenes)
        return summary


class BlenderScenes(MultiViewKind):
    """A user's Blender-format scenes under `dataset.root` (e.g. nerf_synthetic): nothing to render."""

    schema = BlenderDataset
    describes = "a user's Blender-format scenes"
    producer = "stage=render (or dvc repro; for your own scenes, dataset=blender dataset.root=...)"

    def render(self, cfg: DictConfig) -> dict[str, Any]:
        print(f"render: dataset {self.name} is read from {cfg.paths.scenes}; nothing to render")
        return {}
