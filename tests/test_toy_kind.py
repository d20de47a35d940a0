"""A user's own kind of data (tests/plugins/toy_kind.py, tests/conf/dataset/toy_sequence.yaml): small
analytic image sequences, rendered, prepared, trained on and evaluated by the one denoising trainer and
evaluation without any edit under `src/` (issue 31's proof that a data kind is one class and one YAML)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
import torch

from src.errors import ConfigError
from tests.conftest import ROOT, one_line_error, smoke_config
from tests.plugins.toy_kind import clean_frames, split_of

SEARCH = f"hydra.searchpath=[file://{ROOT}/tests/conf]"
FAST = ["metrics.lpips.enabled=false", "metrics.flip.enabled=false", "task.eval.save_exr=false"]


def _cfg(tmp_path, *overrides):
    return smoke_config(tmp_path, tmp_path / "run", [SEARCH, "dataset=toy_sequence", *FAST, *overrides])


def test_the_toy_frames_are_the_analytic_pattern_and_the_noise_shrinks_with_spp(tmp_path):
    from src.stages import render

    cfg = _cfg(tmp_path)
    render(cfg)
    scene = torch.load(tmp_path / "toy_sequence" / "smoke" / "raw" / "scene002.pt", weights_only=True)
    clean = clean_frames(2, 4, 12, 16)  # its own 16 x 12 frames (no still-image profile sizes)
    assert np.array_equal(scene["clean"].numpy(), clean) and clean.min() >= 0.1 - 1e-6
    std = {spp: float((scene["noisy"][str(spp)] - scene["clean"]).std()) for spp in (4, 16)}
    assert std[4] == pytest.approx(0.3 / 2, rel=0.05) and std[16] == pytest.approx(0.3 / 4, rel=0.05)
    assert [split_of(s, 8) for s in range(8)] == ["train"] * 4 + ["val"] * 2 + ["test"] * 2


def test_the_toy_kinds_options_arrive_through_its_constructor_and_its_schema_refuses_a_bad_one(tmp_path):
    """The kind is built from its `dataset:` group, as a method from `model:`: an option set away from its
    default reaches the render (the noise std follows `dataset.noise`), and a value its own schema refuses
    is one line naming the key when the job's task is built, before anything runs."""
    from src.stages import render, task_of

    cfg = _cfg(tmp_path, "dataset.noise=0.8", "dataset.scenes=4")
    kind = task_of(cfg).kind
    assert kind.dataset["noise"] == 0.8 and kind.dataset["scenes"] == 4 and kind.name == "toy_sequence"
    render(cfg)
    raw = sorted(p.name for p in (tmp_path / "toy_sequence" / "smoke" / "raw").glob("*.pt"))
    assert raw == [f"scene{s:03d}.pt" for s in range(4)]
    scene = torch.load(tmp_path / "toy_sequence" / "smoke" / "raw" / "scene001.pt", weights_only=True)
    assert float((scene["noisy"]["4"] - scene["clean"]).std()) == pytest.approx(0.8 / 2, rel=0.05)
    for override, needles in (
        ("dataset.noise=-1.0", ("dataset.noise=-1.0", "positive")),
        ("+dataset.nosie=0.3", ("dataset.nosie",)),
    ):
        with pytest.raises(ConfigError) as excinfo:
            task_of(_cfg(tmp_path, override))
        one_line_error(excinfo, *needles)


def test_a_toy_denoiser_trains_and_is_evaluated_on_the_toy_sequences_with_flicker(tmp_path):
    """Render, preprocess, train (reconstruction + temporal loss) and evaluate in-process; the held-out
    rows have the sequences' frame count and flicker, the curves the kind's loss terms."""
    from src.stages import evaluate, preprocess, render, train
    from src.tracking.tracker import Tracker

    cfg = _cfg(tmp_path, "model=toy")
    render(cfg)
    assert preprocess(cfg)["samples"] == {"train": 12 * 2, "val": 6 * 2}  # 3 windows x 2 spp per scene
    summary = train(cfg, Tracker())
    assert summary["steps"] > 0 and {"train_loss_color", "train_loss_temporal", "val_loss_total"} <= set(
        summary
    )
    result = evaluate(cfg, Tracker())
    rows = pd.read_csv(tmp_path / "run" / "eval" / "per_image.csv")
    assert len(rows) == 4 and set(rows["frames"]) == {4} and rows["temporal"].notna().all()
    assert result["mean"]["psnr"] > 0 and "noisy_temporal" in result["mean"]
    pngs = {p.name for p in (tmp_path / "run" / "eval" / "png").glob("*.png")}
    assert "scene006-f0000-00004spp-denoised.png" in pngs  # frames named as sequences


def test_dpcn_builds_one_radiance_branch_over_the_toy_inputs_and_the_toy_colour_model_is_refused(tmp_path):
    from src.schema.run import validate_run
    from src.tasks.denoise import DenoiseTask

    values = validate_run(_cfg(tmp_path, "model=dpcn"))
    assert values["model"]["branches"] == ["radiance"] and values["model"]["in_channels"] == 4
    cfg = _cfg(tmp_path, "model=toy_color")
    with pytest.raises(ConfigError) as excinfo:
        DenoiseTask.for_run(cfg).check_stages(["train"], cfg)
    one_line_error(excinfo, "model=toy_color", "diffuse branch", "dataset=toy_sequence", "radiance")


@pytest.mark.slow
def test_a_smoke_multirun_trains_evaluates_and_reports_the_toy_denoiser_and_dpcn_on_the_toy_kind(tmp_path):
    """One command, as a user would run it: both models trained and evaluated on the toy sequences, one
    report of their own (reports/denoise-toy/) with the flicker column."""
    import os
    import subprocess
    import sys

    env = {
        **os.environ,
        "NRBENCH_DATA_DIR": str(tmp_path / "data"),
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path}/m.db",
    }
    cmd = [
        sys.executable, "-m", "src.run", "-m", "model=toy,dpcn", "dataset=toy_sequence",
        "hydra.searchpath=[file://tests/conf]", "profile=smoke", *FAST, f"hydra.sweep.dir={tmp_path}/sweep",
        f"tracking.artifact_root={tmp_path}/mlartifacts", f"report.out_dir={tmp_path}/reports",
    ]  # fmt: skip
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    table = pd.read_csv(tmp_path / "reports" / "denoise-toy" / "comparison.csv", comment="#", index_col=0)
    assert sorted(table.index) == ["dpcn", "noisy input", "toy"] and (table["PSNR"] > 0).all()
    assert any("flicker" in c.lower() for c in table.columns), list(table.columns)
    for job in ("0", "1"):
        metrics = json.loads((tmp_path / "sweep" / job / "eval" / "metrics.json").read_text())
        assert metrics["images"] == 4 and metrics["mean"]["temporal"] > 0
        assert set(pd.read_csv(tmp_path / "sweep" / job / "eval" / "per_image.csv")["frames"]) == {4}


def test_a_job_builds_its_data_kind_once_and_every_stage_gets_that_one(tmp_path, monkeypatch):
    """`python -m src.run` in-process (the function under `@hydra.main`), two untracked stages: the kind's
    constructor runs once for the whole job (schema check, job-start settling and both stages)."""
    from src.run import main
    from tests.plugins.toy_kind import ToySequences

    built, used = [], []
    original_init = ToySequences.__init__

    def counting_init(self, **options):
        built.append(self)
        original_init(self, **options)

    def recording(stage):
        method = getattr(ToySequences, stage)

        def run(self, cfg):
            used.append((stage, self))
            return method(self, cfg)

        return run

    monkeypatch.setattr(ToySequences, "__init__", counting_init)
    for stage in ("render", "preprocess"):
        monkeypatch.setattr(ToySequences, stage, recording(stage))
    cfg = _cfg(tmp_path, "task.stages=[render,preprocess]", "stage=all", "tracking.enabled=false")
    results = main.__wrapped__(cfg)
    assert set(results) == {"render", "preprocess"} and results["render"] == {"scenes": 8}
    assert len(built) == 1 and [(s, k is built[0]) for s, k in used] == [
        ("render", True),
        ("preprocess", True),
    ]
