"""The sequence evaluation (`src.eval.denoise_eval.DenoiseEvaluation`) on the `vol_data` fixture's test
sequences with a stub denoiser whose output is known, so that a test can compute every metric by hand:
each reference frame scaled by its own factor (`SCALES`), optionally NaN on one pixel of frame 1 of the
item at one sample count (as a GP expression undefined there), and optionally a second reference (the
reference scaled by `REF2_SCALES`)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from src.eval.denoise_eval import DenoiseEvaluation, OnDevice
from src.tracking.tracker import Tracker
from tests.conftest import data_kind, smoke_config
from tests.test_volume_shards import SPPS, synthetic_frame

#: The stub's output: reference frame f times SCALES[f]; the second reference: times REF2_SCALES[f] (both
#: unequal per frame on purpose, so the temporal metrics see them).
SCALES, REF2_SCALES = torch.tensor([1.0, 0.6, 1.5, 0.8]), torch.tensor([1.1, 0.9, 1.0, 1.2])
BASE = [
    "dataset=volumetric",
    "model=cross_bilateral",
    "metrics.lpips.enabled=false",
    "metrics.flip.enabled=false",
    "task.eval.save_exr=false",
]


class TagTracker(Tracker):
    """A tracker that keeps the tags it is given."""

    def __init__(self):
        super().__init__()
        self.tags: dict[str, str] = {}

    def set_tags(self, tags):
        self.tags |= dict(tags)


@dataclass
class StubEval:
    summary: dict[str, Any]
    logged: dict[str, float]
    rows: pd.DataFrame
    header: dict[str, Any]
    tags: dict[str, str]


def stub_sequence_eval(
    vol_data: Path,
    out: Path,
    monkeypatch,
    overrides=(),
    undefined_spp: int | None = None,
    second_reference: bool = False,
) -> StubEval:
    """Run the evaluation with the stub (module docstring) at the smoke profile plus `overrides`."""
    cfg = smoke_config(vol_data, out, [*BASE, *overrides])

    def infer(self, item):
        output = item["item"]["reference"] * SCALES.view(4, 1, 1, 1)
        if item["item"]["spp"] == undefined_spp:
            output[1, :, 2, 3] = float("nan")
        return output

    def items(self):
        data = self.kind.held_out(self.cfg, self.features, self.model)
        with_second = [dict(data[i]) for i in range(len(data))]
        for item in with_second:
            item["reference2"] = item["reference"] * REF2_SCALES.view(4, 1, 1, 1)
        return OnDevice(with_second, self.device)

    monkeypatch.setattr(DenoiseEvaluation, "infer", infer)
    if second_reference:
        monkeypatch.setattr(DenoiseEvaluation, "items", items)
    tracker = TagTracker()
    evaluation = DenoiseEvaluation(cfg, tracker, data_kind(cfg))
    summary = evaluation.run(desc="stub")
    header = json.loads((out / "eval" / "metrics.json").read_text())
    rows = pd.read_csv(out / "eval" / "per_image.csv")
    return StubEval(summary, evaluation.logged_metrics(summary), rows, header, tracker.tags)


def stub_frames(row) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The raw frames (F, H, W, 3) of a per_image row's test sequence: the stub's output, the noisy input,
    the reference and the second reference."""
    reference = np.stack([synthetic_frame(row.scene, f, max(SPPS))["color"] for f in range(4)])
    noisy = np.stack([synthetic_frame(row.scene, f, row.spp)["color"] for f in range(4)])
    scale = lambda s: s.numpy().reshape(4, 1, 1, 1)  # noqa: E731
    return reference * scale(SCALES), noisy, reference, reference * scale(REF2_SCALES)
