"""scripts/device_check.sh, the GPU check of issue 46, run on the CPU with a tiny frame: every step runs and
writes its card, the cards are collected, and the denoise bench runs carry the device and precision tags
that a report matches its runs' peaks by (src/report/cost_card.py)."""

from __future__ import annotations

import os
import subprocess
import sys

import mlflow
import pytest

from src.report.cost_card import DEVICE_TAG, PRECISION_TAG, measured_peaks
from src.train.device import cpu_model
from tests.conftest import ROOT


@pytest.mark.slow  # 40 s of benches on a tiny frame; the benches themselves are tested by value elsewhere
def test_the_device_check_writes_every_card_and_tags_its_peaks(tmp_path):
    env = {
        **os.environ,
        "DEVICE": "cpu",
        "WIDTH": "48",
        "HEIGHT": "32",
        "ROUNDS": "5",
        "MODELS": "kpcn",  # the default's U-Net KPCN is the slowest to build; the plumbing is the same
        "NERF_MODELS": "nerf,mipnerf",
        "NERF_PROFILE": "smoke",
        "NERF_STEPS": "2",
        "PYTHON": sys.executable,
    }
    out = tmp_path / "check"
    result = subprocess.run(
        ["bash", "scripts/device_check.sh", str(out)], cwd=ROOT, env=env, capture_output=True, text=True
    )
    assert result.returncode == 0, result.stdout + result.stderr
    assert not (out / "failures.txt").exists()
    cards = (out / "cards.md").read_text()
    for name in ("denoise_fp32", "denoise_tf32", "denoise_bf16", "nerf", "nerf_bf16"):
        assert f"## {name}" in cards
    assert "precision fp32" in (out / "denoise_fp32.txt").read_text()
    assert "precision bf16-autocast" in (out / "denoise_bf16.txt").read_text()
    assert "peak memory: host" in (out / "denoise_fp32.txt").read_text()
    assert "kpcn" in cards and "oidn" in cards.lower() and "conv2d" in cards and "train rays/s" in cards
    mlflow.set_tracking_uri(f"sqlite:///{out}/mlflow.db")
    bench = mlflow.search_runs(experiment_names=["nrbench-bench"])
    assert sorted(bench["params.tf32"]) == ["default", "off", "on"]
    assert set(bench[DEVICE_TAG]) == {cpu_model()}  # as a run tags it: the report can match them
    assert sorted(bench[PRECISION_TAG]) == ["bf16-autocast", "fp32", "fp32"]
    assert set(measured_peaks(bench)) == {(cpu_model(), "fp32"), (cpu_model(), "bf16-autocast")}
