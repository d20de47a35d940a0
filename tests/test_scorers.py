"""The evaluation's scorers (src/eval/scorers.py) by value on small hand-made frames: which a run gets,
what each adds to an item's row, and undefined output frames as NaN, never dropped."""

from __future__ import annotations

import typing

import numpy as np
import pytest
import torch

from src.eval.scorers import (
    PROTOCOLS,
    ColorVideoVdp,
    FrameScores,
    NoisebaseProtocol,
    SequenceScores,
    scorers_for,
)
from src.metrics.image import relmse_spp
from src.metrics.temporal import temporal_error
from src.schema.run import Metrics
from tests.conftest import compose_config

FAST = ["metrics.lpips.enabled=false", "metrics.flip.enabled=false"]


def _frames(seed: int, frames: int = 3, size: int = 16) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 2.0, (frames, size, size, 3)).astype(np.float32)


def _images(undefined_frame: int | None = None) -> dict[str, np.ndarray]:
    reference = _frames(0)
    denoised = reference + 0.05 * _frames(1)
    if undefined_frame is not None:
        denoised[undefined_frame, 0, 0, 0] = np.nan
    return {"denoised": denoised, "noisy": reference + 0.5 * _frames(2), "reference": reference}


def _kinds(scorers):
    return [type(s) for s in scorers]


@pytest.mark.parametrize(
    ("overrides", "temporal", "expected"),
    [
        ([], False, [FrameScores]),
        ([], True, [FrameScores, SequenceScores]),
        (["metrics.cvvdp.enabled=true"], True, [FrameScores, SequenceScores, ColorVideoVdp]),
        (["metrics.protocol=noisebase"], True, [FrameScores, SequenceScores, NoisebaseProtocol]),
        (
            ["metrics.cvvdp.enabled=true", "metrics.protocol=noisebase"],
            True,
            [FrameScores, SequenceScores, ColorVideoVdp, NoisebaseProtocol],
        ),
    ],
)
def test_a_run_gets_the_scorers_its_kind_and_metrics_config_ask_for(tmp_path, overrides, temporal, expected):
    cfg = compose_config([*FAST, *overrides])
    assert _kinds(scorers_for(cfg, temporal, torch.device("cpu"), tmp_path)) == expected


def test_the_protocols_the_schema_accepts_are_the_scorers_there_are():
    allowed = typing.get_args(Metrics.model_fields["protocol"].annotation)
    assert {a for arg in allowed for a in typing.get_args(arg)} == set(PROTOCOLS)


def test_frame_scores_are_frame_means_of_the_output_the_noisy_input_and_the_baseline():
    cfg = compose_config(FAST)
    images = _images()
    images["baseline"] = images["reference"] + 0.2 * _frames(3)
    row = FrameScores(cfg.metrics).score({"spp": 4}, images, [True] * 3)
    eps = float(cfg.metrics.relmse_eps)
    for prefix, key in (("", "denoised"), ("noisy_", "noisy"), ("baseline_", "baseline")):
        mse = np.mean([np.mean((images[key][f] - images["reference"][f]) ** 2) for f in range(3)])
        assert row[f"{prefix}mse"] == pytest.approx(mse, rel=1e-5)
    by_hand = np.mean([relmse_spp(images["denoised"][f], images["reference"][f], 4, eps) for f in range(3)])
    assert row["relmse_spp"] == pytest.approx(by_hand, rel=1e-6)
    assert "noisy_relmse_spp" in row and "baseline_relmse_ratio" in row and "baseline_noisy_psnr" not in row


def test_an_undefined_frame_makes_the_outputs_scores_nan_and_the_noisy_inputs_stay():
    cfg = compose_config(FAST)
    images = _images(undefined_frame=1)
    row = FrameScores(cfg.metrics).score({"spp": 4}, images, [True, False, True])
    assert np.isnan(row["psnr"]) and np.isnan(row["relmse_spp"]) and np.isfinite(row["noisy_psnr"])
    sequence = SequenceScores(cfg.metrics).score({"spp": 4}, images, [True, False, True])
    assert np.isnan(sequence["temporal"]) and np.isfinite(sequence["noisy_temporal"])


def test_sequence_scores_are_the_temporal_metrics_of_the_output_and_the_noisy_input():
    cfg = compose_config(FAST)
    images = _images()
    row = SequenceScores(cfg.metrics).score({"spp": 4}, images, [True] * 3)
    m = cfg.metrics
    assert row["temporal"] == temporal_error(images["denoised"], images["reference"], m.tonemap, m.gamma)
    assert row["noisy_temporal"] == temporal_error(images["noisy"], images["reference"], m.tonemap, m.gamma)
    assert set(row) == {"temporal", "tpsnr", "noisy_temporal", "noisy_tpsnr"}  # no second reference
    second = {"spp": 4, "reference2": torch.from_numpy(_frames(4)).permute(0, 3, 1, 2)}
    assert {"flicker_unbiased", "noisy_flicker_unbiased"} <= set(
        SequenceScores(m).score(second, images, [True] * 3)
    )


def test_headers_and_tags_name_the_settings_and_packages_of_the_scorers_that_ran(tmp_path):
    cfg = compose_config([*FAST, "metrics.protocol=noisebase", "metrics.noisebase.warmup=2"])
    protocol = scorers_for(cfg, True, torch.device("cpu"), tmp_path)[-1]
    assert protocol.header()["noisebase_protocol"]["warmup"] == 2
    assert protocol.tags()["nrbench.noisebase.fvvdp"] == str(bool(cfg.metrics.noisebase.fvvdp)).lower()
    assert FrameScores(cfg.metrics).header() == {} and FrameScores(cfg.metrics).tags() == {}
