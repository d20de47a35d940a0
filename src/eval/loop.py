"""The one evaluation loop every task shares (`stage=eval`): the method from its checkpoint, one warm-up
pass, timed inference per item, per-item scores, then `metrics.json` (means), `per_image.csv`,
`provenance.json` and the MLflow metrics and artifacts.

A task's evaluation (`src/eval/denoise_eval.py`, `src/eval/nerf_eval.py`) subclasses `Evaluation` and
supplies what differs: its items, the timed inference, the scores of one item, the images it saves and
any extra summary (the denoisers' means per sample count).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from src.eval.common import mean_rows, sync
from src.io.atomic import atomic_write_csv, atomic_write_json
from src.metrics.image import lpips_variant
from src.models.instantiate import build_method
from src.models.parameters import count_parameters
from src.provenance import provenance
from src.train.checkpoint import load_weights
from src.train.device import pick_device


def load_method(cfg: DictConfig, device: torch.device) -> tuple[torch.nn.Module, dict[str, Any] | None]:
    """Build `cfg.model`; a learned method gets its weights from `task.eval.checkpoint`, checked to match
    the configured architecture. Returns the model (in eval mode) and the checkpoint (None if unlearned)."""
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    model = build_method(model_cfg)
    state = None
    if getattr(model, "learned", True):
        state = load_weights(model, model_cfg, str(cfg.task.eval.checkpoint))
    return model.to(device).eval(), state


class Evaluation:
    """Scores one method on a task's held-out items; `run` does the loop and writes the results."""

    #: What the progress bar counts.
    unit = "img"
    #: Folders under `task.eval.out_dir` logged as MLflow artifacts when present.
    artifact_folders: tuple[str, ...] = ()

    def __init__(self, cfg: DictConfig, tracker) -> None:
        self.cfg, self.tracker = cfg, tracker
        self.device = pick_device(cfg.device)
        self.model, self.checkpoint = load_method(cfg, self.device)
        self.out_dir = Path(cfg.task.eval.out_dir)

    # -- what a task supplies -------------------------------------------------------------------------
    def items(self) -> Sequence[Any]:
        raise NotImplementedError

    def infer(self, item: Any) -> Any:
        """The method's output for one item: what is timed."""
        raise NotImplementedError

    def untimed(self, item: Any, output: Any) -> Any:
        """What `score` and `save_outputs` get from the timed output (e.g. numpy images); not timed."""
        return output

    def score(self, item: Any, output: Any, seconds: float) -> dict[str, Any]:
        """One row of per_image.csv: the item's name, its metrics and its runtime."""
        raise NotImplementedError

    def save_outputs(self, item: Any, output: Any) -> None:
        """Images of one item under `out_dir`."""

    def data_dir(self) -> Path:
        """The data the provenance fingerprints."""
        raise NotImplementedError

    def header(self) -> dict[str, Any]:
        """What metrics.json names before the scores."""
        return {"model": self.cfg.model.name}

    def summarise(self, rows: list[dict[str, Any]]) -> dict[str, Any]:
        return {"images": len(rows), "mean": mean_rows(rows)}

    def logged_metrics(self, summary: dict[str, Any]) -> dict[str, float]:
        """MLflow metrics of the run: `eval_<score>` means and the parameter count."""
        return {f"eval_{k}": v for k, v in summary["mean"].items()} | {"param_count": summary["param_count"]}

    # -- the loop ---------------------------------------------------------------------------------------
    def timed(self, item: Any) -> tuple[Any, float]:
        sync(self.device)
        start = time.perf_counter()
        output = self.infer(item)
        sync(self.device)
        return output, time.perf_counter() - start

    def run(self, desc: str) -> dict[str, Any]:
        """Infer, time, score and save every item; returns (and writes) the summary of means."""
        items = self.items()
        rows: list[dict[str, Any]] = []
        for i in tqdm(range(len(items)), desc=desc, unit=self.unit):
            item = items[i]
            if i == 0:  # warm-up: one-time costs (allocator, OIDN device, kernel selection) are not runtime
                self.infer(item)
            output, seconds = self.timed(item)
            output = self.untimed(item, output)
            rows.append(self.score(item, output, seconds))
            self.save_outputs(item, output)
        summary = {**self.summarise(rows), "param_count": count_parameters(self.model)}
        variant = lpips_variant(self.cfg.metrics)
        if variant is not None:
            summary["lpips_variant"] = variant
        atomic_write_json(self.out_dir / "metrics.json", {**self.header(), **summary})
        # Beside, not inside, metrics.json: DVC reads every number in a metrics file as a metric.
        atomic_write_json(self.out_dir / "provenance.json", provenance(self.cfg, self.data_dir()))
        atomic_write_csv(self.out_dir / "per_image.csv", rows)
        self._log(summary)
        return summary

    def _log(self, summary: dict[str, Any]) -> None:
        self.tracker.log_metrics(self.logged_metrics(summary))
        if "lpips_variant" in summary:
            self.tracker.set_tags({"nrbench.lpips_variant": summary["lpips_variant"]})
        for name in ("metrics.json", "per_image.csv"):
            self.tracker.log_artifact(str(self.out_dir / name), "eval")
        for folder in self.artifact_folders:
            if (self.out_dir / folder).is_dir():
                self.tracker.log_artifacts(str(self.out_dir / folder), f"eval/{folder}")
