"""The held-out scenes' ladder of plain renders (src/data/ladder.py, src/render/ladder_render.py) and the
evaluation's spp-equivalent scorer (src/eval/scorers.py `SppEquivalentScores`): synthetic images of known
per-sample variance give back the sample count they were made at, and "at least" the bound past it; the
smoke dataset's rendered ladder, its cache and its stale files; the evaluation's columns and speed-up."""

from __future__ import annotations

import csv
import json
import math

import numpy as np
import pytest
from omegaconf import OmegaConf

from src.data.ladder import entry_path, ladder_counts, ladder_file, read_ladder
from src.errors import ConfigError, DataError
from src.eval.scorers import SppEquivalentScores, spp_equivalent_scorer
from src.io.exr import write_exr
from src.metrics.spp_equivalent import seconds_per_spp
from tests.conftest import data_kind, one_line_error, smoke_config

COUNTS = [1, 2, 4, 8, 16, 32, 64, 128]
REFERENCE_SPP = 1024
SIZE = (192, 192)


def _metrics(metric="relmse", margin=1.0, crop=0):
    return OmegaConf.create(
        {
            "relmse_eps": 0.01,
            "relmse_crop": crop,
            "spp_equivalent": {"enabled": True, "metric": metric, "margin": margin},
        }
    )


class Scene:
    """A noise-free image and its per-pixel per-sample standard deviation: a render at n spp is the truth
    plus Gaussian noise of variance sigma^2 / n (independent per render)."""

    def __init__(self, frames: int, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)
        shape = (frames, *SIZE, 3)
        self.truth = self.rng.uniform(0.05, 2.0, shape).astype(np.float64)
        self.sigma = self.rng.uniform(0.2, 1.0, shape) * self.truth

    def render(self, spp: float) -> np.ndarray:
        noise = self.rng.standard_normal(self.truth.shape) * self.sigma / math.sqrt(spp)
        return (self.truth + noise).astype(np.float32)


def _write_ladder(ladder_dir, scene: Scene, name: str, temporal: bool, seconds=lambda n: 0.5 + 0.01 * n):
    frames = scene.truth.shape[0]
    for spp in COUNTS:
        image = scene.render(spp)
        for f in range(frames):
            file = ladder_file(name, spp, f if temporal else None)
            write_exr(ladder_dir / file, {c: image[f, ..., i] for i, c in enumerate("RGB")})
            entry = entry_path(ladder_dir, file)
            entry.parent.mkdir(parents=True, exist_ok=True)
            entry.write_text(json.dumps({"spp": spp, "seconds": seconds(spp)}))


@pytest.mark.parametrize(("metric", "temporal"), [("relmse", False), ("mse", False), ("relmse", True)])
@pytest.mark.parametrize("m", [3.0, 24.0, 90.0])
def test_an_image_as_noisy_as_m_samples_reads_m(tmp_path, metric, temporal, m):
    scene = Scene(frames=2 if temporal else 1, seed=int(m))
    _write_ladder(tmp_path, scene, "room-0000", temporal)
    scorer = SppEquivalentScores(_metrics(metric), tmp_path, COUNTS, temporal)
    images = {"reference": scene.render(REFERENCE_SPP), "denoised": scene.render(m), "noisy": scene.render(4)}
    row = scorer.score({"scene": "room-0000", "spp": 4}, images, [True] * scene.truth.shape[0])
    assert row["spp_equivalent"] == pytest.approx(m, rel=0.06)
    assert row["spp_equivalent_at_least"] == 0.0
    assert row["noisy_spp_equivalent"] == pytest.approx(4.0, rel=0.06)
    assert row["ladder_residual"] < 0.05  # Gaussian noise: the law holds on every rung
    assert row["render_s_per_spp"] == pytest.approx(0.01)  # the slope, not the fixed 0.5 s


def test_past_the_ladder_it_is_at_least_the_ladders_top(tmp_path):
    scene = Scene(frames=1, seed=5)
    _write_ladder(tmp_path, scene, "room-0000", False)
    scorer = SppEquivalentScores(_metrics(), tmp_path, COUNTS, False)
    reference = scene.render(REFERENCE_SPP)
    for m, expected in [(400.0, 128.0), (100.0, None)]:  # 400 > the ladder's 128; 100 inside it
        images = {"reference": reference, "denoised": scene.render(m), "noisy": scene.render(4)}
        row = scorer.score({"scene": "room-0000", "spp": 4}, images, [True])
        if expected is None:
            assert row["spp_equivalent_at_least"] == 0.0 and row["spp_equivalent"] == pytest.approx(
                m, rel=0.1
            )
        else:
            assert row["spp_equivalent_at_least"] == 1.0 and row["spp_equivalent"] == expected
            assert row["ladder_limit"] == expected


def test_past_the_references_noise_it_is_at_least_the_references_bound(tmp_path):
    """A reference of 64 spp against a ladder up to 128: the floor c = sigma^2 / 64 bounds the reading at
    a / (margin x c) = 64 / margin spp; the truth itself (error c) reads "at least" that bound."""
    scene = Scene(frames=1, seed=7)
    _write_ladder(tmp_path, scene, "room-0000", False)
    reference = scene.render(64)
    for margin in (1.0, 2.0):
        scorer = SppEquivalentScores(_metrics(margin=margin), tmp_path, COUNTS, False)
        images = {
            "reference": reference,
            "denoised": scene.truth.astype(np.float32),
            "noisy": scene.render(4),
        }
        row = scorer.score({"scene": "room-0000", "spp": 4}, images, [True])
        assert row["spp_equivalent_at_least"] == 1.0
        assert row["spp_equivalent"] == pytest.approx(64.0 / margin, rel=0.08)
    inside = {"reference": reference, "denoised": scene.render(16), "noisy": scene.render(4)}
    row = SppEquivalentScores(_metrics(), tmp_path, COUNTS, False).score(
        {"scene": "room-0000", "spp": 4}, inside, [True]
    )
    assert row["spp_equivalent_at_least"] == 0.0 and row["spp_equivalent"] == pytest.approx(16.0, rel=0.1)


def test_an_undefined_output_has_no_equivalent_and_the_fit_is_made_once_per_scene(tmp_path, monkeypatch):
    scene = Scene(frames=1, seed=3)
    _write_ladder(tmp_path, scene, "room-0000", False)
    scorer = SppEquivalentScores(_metrics(), tmp_path, COUNTS, False)
    reads = []
    import src.eval.scorers as scorers

    real = scorers.read_ladder
    monkeypatch.setattr(scorers, "read_ladder", lambda *a: reads.append(a) or real(*a))
    images = {"reference": scene.render(REFERENCE_SPP), "denoised": scene.render(8), "noisy": scene.render(4)}
    row = scorer.score({"scene": "room-0000", "spp": 4}, images, [False])
    assert math.isnan(row["spp_equivalent"]) and math.isnan(row["spp_equivalent_at_least"])
    assert row["noisy_spp_equivalent"] == pytest.approx(4.0, rel=0.06)
    scorer.score({"scene": "room-0000", "spp": 16}, images, [True])
    assert len(reads) == 1


def test_a_missing_rung_is_one_line_naming_it_and_what_makes_it(tmp_path):
    scene = Scene(frames=1)
    _write_ladder(tmp_path, scene, "room-0000", False)
    (tmp_path / ladder_file("room-0000", 16)).unlink()
    with pytest.raises(DataError) as err:
        read_ladder(tmp_path, "room-0000", COUNTS, None)
    one_line_error(err, "room-0000-00016spp.exr", "stage=render")


@pytest.mark.parametrize(
    ("ladder", "needle"),
    [([1, 1024], "outside 1..1023"), ([0, 4], "outside"), ([8], "at least two counts")],
)
def test_ladder_counts_below_the_reference_and_at_least_two(ladder, needle):
    with pytest.raises(ConfigError) as err:
        ladder_counts({"ladder_spp": ladder, "reference_spp": 1024})
    one_line_error(err, "dataset.ladder_spp", needle)
    assert ladder_counts({"ladder_spp": [4, 1, 4, 1023], "reference_spp": 1024}) == [1, 4, 1023]
    assert ladder_counts({"ladder_spp": None, "reference_spp": 1024}) == []


def test_seconds_per_spp_is_the_slope_and_falls_back_to_the_top_rung():
    assert seconds_per_spp([1, 4, 16, 64], [2.0 + 0.25 * n for n in (1, 4, 16, 64)]) == pytest.approx(0.25)
    # falling times (noise) give no positive slope: the top rung's seconds per sample
    assert seconds_per_spp([1, 4, 16], [3.0, 2.0, 1.6]) == pytest.approx(0.1)
    with pytest.raises(DataError):
        seconds_per_spp([4, 4], [1.0, 1.0])
    # a rung without a time (a ladder averaged from stored samples): no cost per sample, so no speed-up
    assert math.isnan(seconds_per_spp([1, 4, 16], [1.0, float("nan"), 4.0]))


def test_the_ladder_job_start_check_is_one_line(tmp_path):
    from src.schema.run import validate_run

    cfg = smoke_config(tmp_path, tmp_path / "run", ["dataset.ladder_spp=[1,128]"])
    with pytest.raises(ConfigError) as err:
        validate_run(cfg)
    one_line_error(err, "dataset.ladder_spp", "below")


# -- the smoke dataset's rendered ladder and the evaluation ---------------------------------------------


def test_the_render_stage_renders_the_held_out_scenes_ladder_once(smoke_data, tmp_path):
    cfg = smoke_config(smoke_data, tmp_path / "run")
    kind = data_kind(cfg)
    held_out = kind.ladder_scenes(cfg)
    assert held_out == kind.scene_splits(cfg)["test"] and held_out
    ladder_dir = smoke_data / "procedural" / "smoke" / "ladder"
    counts = list(cfg.dataset.ladder_spp)
    made = sorted(p.name for p in ladder_dir.glob("*.exr"))
    assert made == sorted(ladder_file(s, n) for s in held_out for n in counts)
    ladder = read_ladder(ladder_dir, held_out[0], counts, None)
    assert ladder.frames[1].shape == (1, cfg.dataset.height, cfg.dataset.width, 3)
    assert all(ladder.seconds[n] > 0 for n in counts)
    # a rung at a noisy input's count is another render (its own seeds): the noisy check is independent
    from src.io.exr import read_exr

    noisy = read_exr(smoke_data / "procedural" / "smoke" / "raw" / f"{held_out[0]}-00004spp.exr", "RGB")
    noisy = np.stack([noisy[c] for c in "RGB"], axis=-1)
    assert noisy.shape == ladder.frames[4][0].shape and not np.allclose(noisy, ladder.frames[4][0])
    from src.stages import render

    assert render(cfg)["ladder"]["files_rendered"] == 0  # current: kept


def test_a_changed_ladder_renders_only_the_new_rungs_and_removes_the_dropped(smoke_data, tmp_path):
    import shutil

    from src.stages import render

    data = tmp_path / "data"
    shutil.copytree(smoke_data / "procedural", data / "procedural")
    cfg = smoke_config(data, tmp_path / "run", ["dataset.ladder_spp=[2,4,8,16,32,64,96]"])
    summary = render(cfg)["ladder"]
    held_out = data_kind(cfg).ladder_scenes(cfg)
    assert summary["files_rendered"] == len(held_out)  # 96 is new; the others are current
    names = sorted(p.name for p in (data / "procedural" / "smoke" / "ladder").glob("*.exr"))
    assert names == sorted(ladder_file(s, n) for s in held_out for n in [2, 4, 8, 16, 32, 64, 96])
    off = smoke_config(data, tmp_path / "run", ["dataset.ladder_spp=[]"])
    assert render(off)["ladder"]["files_removed"] == len(names)
    assert not list((data / "procedural" / "smoke" / "ladder").glob("*.exr"))


def test_the_evaluation_scores_the_equivalent_and_the_speedup(smoke_data, tmp_path):
    from src.eval.denoise_eval import evaluate_denoiser
    from src.tracking.mlflow_tracking import job_run

    cfg = smoke_config(smoke_data, tmp_path / "run", ["model=cross_bilateral", "tracking.enabled=false"])
    with job_run(cfg, run_name="x", tags={}) as tracker:
        summary = evaluate_denoiser(cfg, tracker, data_kind(cfg))
    with open(tmp_path / "run" / "eval" / "per_image.csv") as f:
        rows = list(csv.DictReader(f))
    assert rows
    for row in rows:
        value, spp = float(row["spp_equivalent"]), int(row["spp"])
        s_per_spp, denoise_s = float(row["render_s_per_spp"]), float(row["ms_per_image"]) / 1e3
        assert float(row["speedup"]) == pytest.approx(value * s_per_spp / (spp * s_per_spp + denoise_s))
        # the noisy input, an independent render at `spp`, reads about its own count (smoke: 1.6x)
        assert abs(math.log(float(row["noisy_spp_equivalent"]) / spp)) < math.log(1.6)
    for spp, means in summary["per_spp"].items():
        values = [float(r["spp_equivalent"]) for r in rows if int(r["spp"]) == int(spp)]
        assert means["spp_equivalent"] == pytest.approx(math.exp(np.mean(np.log(values))))
    overall = [float(r["speedup"]) for r in rows]  # the overall mean of a ratio is geometric too
    assert summary["mean"]["speedup"] == pytest.approx(math.exp(np.mean(np.log(overall))))
    assert summary["mean"]["speedup"] != pytest.approx(np.mean(overall))
    metrics = json.loads((tmp_path / "run" / "eval" / "metrics.json").read_text())
    header = metrics["spp_equivalent"]
    assert header["metric"] == "relmse" and header["ladder_spp"] == list(cfg.dataset.ladder_spp)
    # the cost card's achieved GFLOP/s: the filter's FLOPs per pixel over the timed seconds of each image
    pixels = cfg.dataset.width * cfg.dataset.height
    assert metrics["flops_per_pixel"] > 0
    for row in rows:
        seconds = float(row["ms_per_image"]) / 1e3
        assert float(row["gflops"]) == pytest.approx(metrics["flops_per_pixel"] * pixels / seconds / 1e9)


def test_the_scorer_is_left_out_without_a_ladder(smoke_data, tmp_path):
    def scorer(*overrides, data=smoke_data):
        return spp_equivalent_scorer(smoke_config(data, tmp_path / "run", list(overrides)), False)

    assert isinstance(scorer(), SppEquivalentScores)
    assert scorer("metrics.spp_equivalent.enabled=false") is None
    assert scorer("dataset.ladder_spp=[]") is None
    assert scorer(data=tmp_path / "elsewhere") is None  # never rendered: a user's own EXRs
    chosen = scorer("metrics.spp_equivalent.metric=mse", "metrics.spp_equivalent.margin=3")
    assert (chosen.metric, chosen.margin) == ("mse", 3.0)


def test_mse_and_relmse_read_their_own_equivalents(tmp_path):
    """Bright pixels denoised to 100 spp, dark ones to 4: MSE, ruled by the bright pixels, reads about 100;
    relMSE, which weighs each pixel by 1 / (reference^2 + eps), reads far less. Each equals the closed form
    n* = mean(w sigma^2) / mean(w sigma^2 / m) with its weights w (reference = truth: no floor)."""
    scene = Scene(frames=1, seed=11)
    bright = np.zeros(scene.truth.shape, bool)
    bright[:, : SIZE[0] // 2] = True
    scene.truth = np.where(bright, 10.0, 0.1)
    scene.sigma = 0.5 * scene.truth
    _write_ladder(tmp_path, scene, "room-0000", False)
    m = np.where(bright, 100.0, 4.0)
    denoised = (scene.truth + scene.rng.standard_normal(scene.truth.shape) * scene.sigma / np.sqrt(m)).astype(
        np.float32
    )
    images = {"reference": scene.truth.astype(np.float32), "denoised": denoised, "noisy": scene.render(4)}
    for metric, weight in [("mse", np.ones_like(scene.truth)), ("relmse", 1 / (scene.truth**2 + 0.01))]:
        row = SppEquivalentScores(_metrics(metric), tmp_path, COUNTS, False).score(
            {"scene": "room-0000", "spp": 4}, images, [True]
        )
        expected = np.mean(weight * scene.sigma**2) / np.mean(weight * scene.sigma**2 / m)
        assert row["spp_equivalent"] == pytest.approx(expected, rel=0.06), metric
    assert expected < 20  # relMSE's reading is far from MSE's ~100: the two metrics are told apart


def test_geometric_means_replace_the_arithmetic_ones_of_ratios():
    from src.eval.denoise_eval import geometric_means

    rows = [{"spp_equivalent": 4.0, "speedup": 1.0}, {"spp_equivalent": 64.0, "speedup": float("nan")}]
    means = geometric_means(rows, {"spp_equivalent": 34.0, "speedup": 1.0, "psnr": 30.0})
    assert means == {"spp_equivalent": pytest.approx(16.0), "speedup": 1.0, "psnr": 30.0}


def test_sequences_score_every_frame_against_the_ladder_and_time_per_frame(tmp_path, mitsuba_variant):
    """dataset=volumetric at the smoke profile, two held-out sequences: their ladders of every frame, the
    speed-up from the denoising seconds per frame, the per-spp geometric means over the two."""
    from src.eval.denoise_eval import evaluate_denoiser
    from src.stages import preprocess, render
    from src.tracking.mlflow_tracking import job_run

    overrides = [
        "dataset=volumetric",
        "model=cross_bilateral",
        "tracking.enabled=false",
        "task.preprocess.split={train: 0.4, val: 0.2, test: 0.4}",
    ]
    cfg = smoke_config(tmp_path / "data", tmp_path / "run", overrides)
    kind = data_kind(cfg)
    assert len(kind.ladder_scenes(cfg)) == 2
    render(cfg)
    preprocess(cfg)
    with job_run(cfg, run_name="x", tags={}) as tracker:
        summary = evaluate_denoiser(cfg, tracker, kind)
    with open(tmp_path / "run" / "eval" / "per_image.csv") as f:
        rows = list(csv.DictReader(f))
    assert sorted({r["scene"] for r in rows}) == kind.ladder_scenes(cfg)
    for row in rows:
        frames, spp, value = int(row["frames"]), int(row["spp"]), float(row["spp_equivalent"])
        assert frames == cfg.dataset.frames
        s_per_spp, denoise_s = float(row["render_s_per_spp"]), float(row["ms_per_image"]) / 1e3  # per frame
        assert float(row["speedup"]) == pytest.approx(value * s_per_spp / (spp * s_per_spp + denoise_s))
        assert abs(math.log(float(row["noisy_spp_equivalent"]) / spp)) < math.log(1.6)
    for spp, means in summary["per_spp"].items():
        values = [float(r["spp_equivalent"]) for r in rows if int(r["spp"]) == int(spp)]
        assert len(values) == 2 and values[0] != values[1]
        assert means["spp_equivalent"] == pytest.approx(math.exp(np.mean(np.log(values))))


def _image_rows():
    """Per-image rows as `collect.per_image_rows` gives them: two models, two seeds (runs), two images,
    input counts 4 and 16."""
    import pandas as pd

    rows = []
    for model, factor in [("kpcn", 2.0), ("unet_kpcn", 4.0)]:
        for seed in (0, 1):
            for scene, scale in [("a", 1.0), ("b", 4.0)]:
                for spp in (4, 16):
                    value = spp * factor * scale * (1 + seed)
                    rows.append(
                        {
                            "params.model.name": model,
                            "run_id": f"{model}-{seed}",
                            "scene": scene,
                            "spp": spp,
                            "metrics.spp_equivalent": value,
                            "metrics.spp_equivalent_at_least": float(value >= 256),
                            "metrics.speedup": value / spp / 2,
                            "metrics.noisy_spp_equivalent": spp * 1.1,
                            "metrics.ladder_residual": 0.1 * scale,
                        }
                    )
    return pd.DataFrame(rows)


def test_the_samples_saved_table_is_geometric_over_images_and_seeds():
    from src.report.samples_saved import best_per_spp, samples_saved_table

    table = samples_saved_table(_image_rows(), ["model.name"])
    kpcn4 = table.loc[("kpcn", 4)]
    values = [4 * 2.0 * s * k for s in (1.0, 4.0) for k in (1, 2)]  # 8, 16, 32, 64
    assert kpcn4["spp-equivalent"] == pytest.approx(math.exp(np.mean(np.log(values))))
    assert (kpcn4["min"], kpcn4["max"], kpcn4["images"], kpcn4["runs"]) == (8.0, 64.0, 4.0, 2)
    assert kpcn4["speed-up"] == pytest.approx(kpcn4["spp-equivalent"] / 8)
    assert kpcn4["noisy reads"] == pytest.approx(4.4) and kpcn4["ladder residual"] == pytest.approx(0.4)
    unet16 = table.loc[("unet_kpcn", 16)]
    assert unet16["lower bounds"] == 0.5  # 64 and 128 read, 256 and 512 "at least"
    assert list(table.index.get_level_values("spp")) == [4, 4, 16, 16]
    best = best_per_spp(table)  # within each input count: the U-Net rows, never across counts
    assert best["spp-equivalent"] == {1, 3} and best["speed-up"] == {1, 3}


def test_the_samples_saved_table_is_left_out_without_equivalents():
    from src.report.samples_saved import samples_saved_table

    rows = _image_rows()
    assert samples_saved_table(rows.iloc[0:0], ["model.name"]) is None
    assert samples_saved_table(rows.drop(columns="metrics.spp_equivalent"), ["model.name"]) is None
