"""`dvc repro` end to end in a temporary copy of the repository, smoke profile (slow: minutes, about
forty `python -m src.run` processes; run with `pytest -m slow`)."""

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from omegaconf import OmegaConf

from tests.conftest import ROOT

pytestmark = pytest.mark.slow


def _copy_repository(dst: Path) -> None:
    """The working tree's tracked and non-ignored files (what a fresh clone plus local edits has)."""
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
        cwd=ROOT,
        capture_output=True,
        check=True,
    ).stdout.decode()
    for name in filter(None, listed.split("\0")):
        if (ROOT / name).is_file():
            (dst / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(ROOT / name, dst / name)
    subprocess.run(["git", "init", "-q"], cwd=dst, check=True)


def _dvc(repo: Path, *args: str) -> str:
    env = dict(os.environ)
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env['PATH']}"  # stages call `python`
    env.pop("MLFLOW_TRACKING_URI", None)  # the copy's own mlflow.db
    env.pop("NRBENCH_DATA_DIR", None)
    result = subprocess.run(
        [sys.executable, "-m", "dvc", *args], cwd=repo, env=env, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result.stdout


def test_dvc_repro_runs_everything_then_nothing(tmp_path):
    repo = tmp_path / "repo"
    repo.mkdir()
    _copy_repository(repo)
    params = repo / "params.yaml"
    params.write_text(params.read_text().replace("profile: cpu", "profile: smoke"))

    _dvc(repo, "repro")
    compare = OmegaConf.load(ROOT / "conf" / "compare.yaml")  # what dvc.yaml's stages loop over
    nerf_runs = [f"{m}-{s}" for m in compare.nerf.models for s in compare.nerf.scenes]
    for task, names in (
        ("denoise", [*compare.denoise.learned, *compare.denoise.baselines]),
        ("nerf", nerf_runs),
        ("volumetric", [*compare.volumetric.learned, *compare.volumetric.baselines]),
    ):
        for name in names:
            metrics = json.loads((repo / "runs" / task / name / "eval" / "metrics.json").read_text())
            assert metrics["mean"]["psnr"] > 0, (task, name)
        report = repo / "reports" / task
        assert (report / "index.html").is_file() and (report / "comparison.md").is_file()
        table = (report / "comparison.csv").read_text()
        assert all(m.split("-")[0] in table for m in names)
    flicker = json.loads((repo / "runs" / "volumetric" / "unet_kpcn" / "eval" / "metrics.json").read_text())
    assert flicker["mean"]["temporal"] >= 0  # every volumetric table has the flicker column
    selection = repo / "data" / "volumetric" / "smoke" / "feature_selection"  # params.yaml's profile
    assert (selection / "selection.json").is_file() and (selection / "selection.csv").is_file()
    shown = json.loads(_dvc(repo, "metrics", "show", "--json"))
    assert "runs/denoise/kpcn/eval/metrics.json" in shown[""]["data"]

    again = _dvc(repo, "repro")
    assert "Running stage" not in again, again
    assert "up to date" in _dvc(repo, "status")

    # One model's config changes: its train/eval stages and the report rerun, no other model's.
    budget = repo / "conf" / "model_task_profile" / "resnet_smoke.yaml"  # a model's task settings
    budget.write_text("# @package task\ntrain:\n  lr: 2.0e-4\n")
    changed = _dvc(repo, "repro")
    ran = set(re.findall(r"Running stage '([^']+)'", changed))
    assert {"denoise_train@resnet", "denoise_eval@resnet", "denoise_report"} <= ran, ran
    assert "nerf_report" not in ran, ran
    # resnet also runs per frame on the volumetric sequences: those two stages rerun too, no other model's.
    assert not {s for s in ran if re.match(r"(denoise|nerf|vol)_(train|eval)", s)} - {
        "denoise_train@resnet",
        "denoise_eval@resnet",
        "vol_train@resnet",
        "vol_eval@resnet",
    }, ran
