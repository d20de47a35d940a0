"""`task.eval.baseline`: a filter scored beside the run's method on the same frames (the filter search's
constant-sigma cross-bilateral filter, conf/task/filter_search.yaml), in per_image.csv as `baseline_<metric>`
and in MLflow as `eval_baseline_<metric>`."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from src.errors import ConfigError
from src.metrics.image import psnr, relmse_spp, tonemap
from src.models.filters.cross_bilateral import CrossBilateralFilter
from tests.conftest import one_line_error
from tests.sequence_eval_stub import stub_frames, stub_sequence_eval
from tests.test_flicker_metrics import TONEMAP

# Wide range sigmas: near a box filter of radius 2, which changes the synthetic frames (the defaults leave
# their noise as it is).
SIGMAS = {
    "sigma_spatial": 2.0,
    "sigma_color": 50.0,
    "sigma_normal": 50.0,
    "sigma_albedo": 50.0,
    "sigma_depth": 50.0,
}
BASELINE = (
    "+task.eval.baseline={name: cross_bilateral, "
    "_target_: src.models.filters.cross_bilateral.CrossBilateralFilter, radius: 2, "
    + ", ".join(f"{k}: {v}" for k, v in SIGMAS.items())
    + "}"
)


def _filtered(vol_data, row) -> np.ndarray:
    """The baseline's frames of a row's test item, filtered here from the prepared item's tensors."""
    from tests.conftest import data_kind, smoke_config

    cfg = smoke_config(vol_data, vol_data / "_cfg", ["dataset=volumetric", "model=cross_bilateral"])
    kind = data_kind(cfg)
    model = CrossBilateralFilter(radius=2, **SIGMAS)
    items = kind.held_out(cfg, kind.features(cfg), model)
    item = next(items[i] for i in range(len(items)) if items[i]["spp"] == row.spp)
    batch = {k: v for k, v in item.items() if isinstance(v, torch.Tensor)}
    frames = [
        model({k: v[f : f + 1] for k, v in batch.items()})["color"] for f in range(batch["color"].shape[0])
    ]
    return torch.cat(frames).permute(0, 2, 3, 1).numpy()


def test_the_baseline_is_scored_on_the_same_frames_as_the_method(vol_data, tmp_path, monkeypatch):
    run = stub_sequence_eval(vol_data, tmp_path, monkeypatch, [*TONEMAP, BASELINE])
    logged, rows = run.logged, run.rows
    for row in rows.itertuples():
        denoised, noisy, reference, _ = stub_frames(row)
        baseline = _filtered(vol_data, row)
        ldr = lambda x: tonemap(x, "reinhard_gamma", 2.2)  # noqa: E731
        expected_psnr = np.mean([psnr(ldr(baseline[f]), ldr(reference[f])) for f in range(4)])
        expected_relmse = np.mean([relmse_spp(baseline[f], reference[f], row.spp, 0.01) for f in range(4)])
        assert row.baseline_psnr == pytest.approx(expected_psnr, rel=1e-4)
        assert row.baseline_relmse_spp == pytest.approx(expected_relmse, rel=1e-4)
        noisy_relmse = np.mean([relmse_spp(noisy[f], reference[f], row.spp, 0.01) for f in range(4)])
        assert row.baseline_relmse_ratio == pytest.approx(expected_relmse / noisy_relmse, rel=0.05)
        assert abs(row.baseline_psnr - row.psnr) > 0.5  # the stub's output and the filter's differ
        assert abs(row.baseline_psnr - row.noisy_psnr) > 0.5  # and the filter changes its input
    assert "baseline_noisy_relmse_spp" not in rows  # the noisy input is scored once
    assert run.header["baseline"] == "cross_bilateral"  # metrics.json names the baseline
    assert logged["eval_baseline_psnr"] == pytest.approx(rows["baseline_psnr"].mean(), rel=1e-12)
    spp = int(rows.spp.iloc[0])
    assert logged[f"eval_baseline_relmse_spp_spp{spp}"] == pytest.approx(rows.baseline_relmse_spp.iloc[0])


def test_without_a_baseline_there_are_no_baseline_columns(vol_data, tmp_path, monkeypatch):
    run = stub_sequence_eval(vol_data, tmp_path, monkeypatch, TONEMAP)
    logged, rows = run.logged, run.rows
    assert not [c for c in rows if c.startswith("baseline_")]
    assert not [k for k in logged if "baseline" in k]


def test_the_cost_card_of_a_sequence_evaluation_and_the_tags_of_every_scorer(vol_data, tmp_path, monkeypatch):
    """Per item: ms per megapixel and GFLOP/s over the item's 4 frames, from the FLOPs per pixel probed
    with the data's input channels; metrics.json and the logged metrics carry the probe's number; the tags
    of two scorers (ColorVideoVDP, the Noisebase protocol) both arrive."""
    import src.eval.denoise_eval as denoise_eval

    asked = {}

    def probe(model, in_channels=None):
        asked["in_channels"] = in_channels
        return {"total": 1234.0}

    monkeypatch.setattr(denoise_eval, "flops_per_pixel", probe)
    extra = ["metrics.cvvdp.enabled=true", "metrics.protocol=noisebase", "metrics.noisebase.warmup=1"]
    run = stub_sequence_eval(
        vol_data, tmp_path, monkeypatch, [*TONEMAP, *extra, "metrics.noisebase.fvvdp=false"]
    )
    from tests.conftest import smoke_config

    channels = smoke_config(vol_data, tmp_path, ["dataset=volumetric"]).dataset.input_channels
    assert asked["in_channels"] == channels and channels != 3
    assert run.header["flops_per_pixel"] == 1234.0 and run.logged["eval_flops_per_pixel"] == 1234.0
    for row in run.rows.itertuples():
        frames, (height, width) = row.frames, stub_frames(row)[2].shape[1:3]
        assert frames == 4
        assert row.ms_per_mpixel == pytest.approx(row.ms_per_image / (height * width / 1e6))
        assert row.gflops == pytest.approx(1234.0 * height * width / (row.ms_per_image / 1e3) / 1e9)
    assert "nrbench.cvvdp.version" in run.tags and "nrbench.noisebase.pyfvvdp" in run.tags


def test_a_model_the_flops_probe_cannot_run_has_no_gflops_and_says_so(
    vol_data, tmp_path, monkeypatch, caplog
):
    import src.eval.denoise_eval as denoise_eval

    def probe(model, in_channels=None):
        raise RuntimeError("inputs of its own")

    monkeypatch.setattr(denoise_eval, "flops_per_pixel", probe)
    run = stub_sequence_eval(vol_data, tmp_path, monkeypatch, TONEMAP)
    assert run.header["flops_per_pixel"] is None and "gflops" not in run.rows
    assert "eval_flops_per_pixel" not in run.logged
    assert "FLOPs per pixel of model=cross_bilateral unknown (inputs of its own)" in caplog.text


def test_every_frame_is_saved_as_exr_and_tone_mapped_pngs_and_the_middle_frame_as_a_strip(
    vol_data, tmp_path, monkeypatch
):
    """With `task.eval.save_exr` and a gamma away from its default: each frame's EXR holds the output's
    R, G, B; its PNGs are the tone map of the images at that gamma (an undefined pixel black); only the
    middle frame (2 of 4) has a comparison strip."""
    from PIL import Image

    from src.io.exr import read_exr

    overrides = [*TONEMAP, "task.eval.save_exr=true", "metrics.gamma=1.6"]
    run = stub_sequence_eval(vol_data, tmp_path, monkeypatch, overrides, undefined_spp=8)
    out = tmp_path / "eval"
    for row in run.rows.itertuples():
        denoised, noisy, reference, _ = stub_frames(row)
        if row.spp == 8:
            denoised[1, 2, 3, :] = np.nan  # the stub's undefined pixel (its (F, C, H, W) [1, :, 2, 3])
        for f in range(4):
            name = f"{row.scene}-f{f:04d}-{row.spp:05d}spp"
            exr = read_exr(out / "images" / f"{name}.exr")
            got = np.stack([exr[c] for c in "RGB"], -1)
            np.testing.assert_allclose(got, denoised[f], rtol=1e-6, equal_nan=True)
            for kind, image in (("noisy", noisy[f]), ("denoised", denoised[f]), ("reference", reference[f])):
                png = np.asarray(Image.open(out / "png" / f"{name}-{kind}.png"), dtype=np.float64)
                want = np.round(255 * np.clip(tonemap(np.nan_to_num(image), "reinhard_gamma", 1.6), 0, 1))
                np.testing.assert_allclose(png, want, atol=1, err_msg=f"{name} {kind}")
            assert (out / "strips" / f"{name}.png").exists() == (f == 2)
        if row.spp == 8:
            png = np.asarray(Image.open(out / "png" / f"{row.scene}-f0001-00008spp-denoised.png"))
            assert not png[2, 3].any()  # NaN drawn black


def test_a_learned_baseline_is_a_one_line_error(vol_data, tmp_path, monkeypatch):
    learned = "+task.eval.baseline={name: identity, _target_: torch.nn.Identity}"  # no `learned = False`
    with pytest.raises(ConfigError) as excinfo:
        stub_sequence_eval(vol_data, tmp_path, monkeypatch, [learned])
    one_line_error(excinfo, "task.eval.baseline", "learned")


@pytest.mark.parametrize(("frames", "middle"), [(5, 2), (4, 2), (1, 0)])
def test_the_strip_is_the_middle_frames_for_odd_and_even_lengths(frames, middle, tmp_path, monkeypatch):
    """Of F frames, frame F // 2 alone gets the comparison strip: 2 of 5, 2 of 4, the only one of 1."""
    from types import SimpleNamespace

    from omegaconf import OmegaConf

    from src.eval import denoise_eval

    saved = {}
    monkeypatch.setattr(
        denoise_eval, "_save_images", lambda out, item, images, e, m: saved.update({item["scene"]: e.strips})
    )
    evaluation = object.__new__(denoise_eval.DenoiseEvaluation)  # only what save_outputs reads
    evaluation.cfg = OmegaConf.create({"task": {"eval": {"strips": True}}, "metrics": {}})
    evaluation.kind, evaluation.out_dir = SimpleNamespace(temporal=True), tmp_path
    images = {k: np.zeros((frames, 2, 2, 3)) for k in ("noisy", "denoised", "reference")}
    evaluation.save_outputs({"item": {"scene": "s", "spp": 4}}, images)
    assert saved == {f"s-f{f:04d}": f == middle for f in range(frames)}


# Mutation testing (scripts/mutation.sh denoise_eval): the mutants left alive, against this group's files
# (this one, tests/test_ladder.py, tests/test_flicker_metrics.py):
# - equivalent: `nan_to_num` without `nan=0.0` (numpy's default), `device=None` / `.to(None)` (the CPU),
#   the progress bar's `desc`, the strip's panel label "denoised" (text in an image), the baseline's
#   `build_method(section=..., resolve=...)` (the section only names a key in build errors; the shipped
#   baselines have no interpolations), the FLOPs divisor 1e9 + 1 (a 1e-9 change, inside every tolerance);
# - not reached by these files, tested elsewhere: `check_trained_features`' arguments (the stub's filter
#   has no checkpoint; tests/test_data_kinds.py refuses a checkpoint of other features in each kind), the
#   data's colour space (the stub replaces inference; the trained models' evaluations in
#   tests/test_denoise_train.py and tests/test_volumetric_training.py use it), a still image's file names
#   (the stills' evaluations in tests/test_ladder.py and tests/test_report.py);
# - the FLOPs probe without input channels: that branch is gone (the run schema requires
#   `dataset.input_channels`, so it could not be reached);
# - `f == frames / 2` for `frames // 2` (an odd-length sequence then got no strip): now killed by
#   test_the_strip_is_the_middle_frames_for_odd_and_even_lengths.
