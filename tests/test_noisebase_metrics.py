"""The Noisebase scoring protocol (src/metrics/noisebase_protocol.py) equals the `noisebase` package's own
metric code (`noisebase/scripts/nb_compute_metrics.py`, `noisebase/metrics/flip.py`, `fvvdp.py`) on the
same 8-bit frames, to 1e-6; closed forms; the warm-up drops the first 16 frames.

The package's FLIP allocates on CUDA (`.cuda()`, `device='cuda'`): the `theirs` fixture runs it on the
CPU by making those calls stay on the CPU for the test's duration (nothing else in it changes)."""

from __future__ import annotations

import importlib
import importlib.metadata
import json
import math
import sys

import numpy as np
import pandas as pd
import pytest
import torch

from src.errors import ConfigError, DataError
from src.metrics import noisebase_protocol as nbp
from src.report.noisebase_table import best_measured, noisebase_table
from src.report.table_writers import to_markdown
from src.schema.run import validate_run
from tests.conftest import one_line_error, smoke_config
from tests.sequence_eval_stub import SCALES, stub_sequence_eval
from tests.test_volume_shards import SPPS, synthetic_frame

H, W = 168, 176  # MS-SSIM's five scales need >= 161 pixels a side


@pytest.fixture
def theirs(monkeypatch):
    """`noisebase.scripts.nb_compute_metrics` (after the pyfvvdp shim), its CUDA allocations on the CPU."""
    real_zeros = torch.zeros

    def zeros(*args, device=None, **kwargs):
        return real_zeros(*args, device=None if str(device).startswith("cuda") else device, **kwargs)

    monkeypatch.setattr(torch, "zeros", zeros)
    monkeypatch.setattr(torch.Tensor, "cuda", lambda self, *args, **kwargs: self)
    nbp.import_pyfvvdp()
    return importlib.import_module("noisebase.scripts.nb_compute_metrics")


def _pair(frames: int, height: int = H, width: int = W, seed: int = 0, noise: int = 30):
    """Reference frames that drift from frame to frame, and a test = reference + 8-bit noise (uint8)."""
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (height, width, 3))
    ref = np.stack([np.clip(base + 12 * f + rng.integers(-8, 9, base.shape), 0, 255) for f in range(frames)])
    test = np.clip(ref + rng.integers(-noise, noise + 1, ref.shape), 0, 255)
    return test.astype(np.uint8), ref.astype(np.uint8)


def test_srgb8_equals_noisebase_saved_png_values():
    from noisebase.data import ACES

    rng = np.random.default_rng(1)
    hdr = rng.lognormal(-1.0, 2.5, (40, 60, 3)).astype(np.float32)
    hdr[0, :5] = 0.0  # black
    hdr[1, :5] = 1e6  # far above white
    hdr[2, :5] = [-1.0, 0.5, 0.0]  # a negative channel: as their ACES maps it
    ours = nbp.srgb8(hdr)
    assert ours.dtype == np.uint8
    np.testing.assert_array_equal(ours, (ACES(hdr) * 255).astype(np.uint8))
    assert (ours[0, :5] == 0).all() and (ours[1, :5] == 255).all()
    assert len(np.unique(ours)) > 200  # the random frame spans the 8-bit range


def test_to_unit_equals_their_np_to_torch(theirs):
    test, _ = _pair(1)
    assert torch.equal(nbp.to_unit(test[0]), theirs.np_to_torch(test[0]))


@pytest.mark.parametrize("name", ["mse", "psnr", "ssim", "msssim", "rmae"])
def test_per_frame_metrics_equal_theirs(theirs, name):
    test, ref = _pair(2)
    for f in range(2):
        t, r = theirs.np_to_torch(test[f]), theirs.np_to_torch(ref[f])
        expected = getattr(theirs, name)(t, r)
        assert getattr(nbp, name)(t, r) == pytest.approx(expected, abs=1e-6)
    assert math.isfinite(expected) and expected != 0


def test_flip_equals_their_pytorch_flip(theirs):
    from noisebase.metrics.flip import flip

    test, ref = _pair(1, 64, 80, seed=3, noise=60)
    t, r = nbp.to_unit(test[0]), nbp.to_unit(ref[0])
    expected = flip(t, r)
    assert 0.05 < expected < 0.5
    assert nbp.flip(t, r) == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize("name", ["psnr", "rmae"])
def test_temporal_metrics_equal_their_adapter(theirs, name):
    test, ref = _pair(4, 32, 40, seed=4)
    out, reference = [nbp.to_unit(f) for f in test], [nbp.to_unit(f) for f in ref]
    adapter = theirs.TemporalMetricAdapter(getattr(theirs, name))
    for t, r in zip(out, reference, strict=True):
        adapter.feed(t, r)
    expected = adapter.compute()
    assert nbp.temporal(getattr(nbp, name), out, reference) == pytest.approx(expected, abs=1e-6)
    # Not the spatial metric of the frames themselves: the differences are what is scored.
    spatial = np.mean([getattr(nbp, name)(t, r) for t, r in zip(out[1:], reference[1:], strict=True)])
    assert abs(spatial - expected) > 1e-3


def test_fovvideovdp_equals_their_feeder(theirs):
    from noisebase.metrics.fvvdp import nb_fvvdp

    test, ref = _pair(5, 48, 64, seed=5)
    out, reference = [nbp.to_unit(f) for f in test], [nbp.to_unit(f) for f in ref]
    feeder = nb_fvvdp(display_name="standard_fhd").video_feeder(48, 64, 5, 30)
    for t, r in zip(out, reference, strict=True):
        feeder.feed(t, r)
    expected = feeder.compute()
    assert 0 < expected < 9.9  # a visible difference
    assert nbp.fovvideovdp(out, reference) == pytest.approx(expected, abs=1e-6)
    assert nbp.fovvideovdp(reference, reference) == pytest.approx(10.0, abs=1e-4)  # identical: 10 JOD


@pytest.mark.parametrize(("frames", "fps"), [(5, 8.0), (1, 30.0)])
def test_fovvideovdp_equals_their_feeder_at_another_rate_and_on_one_frame(theirs, frames, fps):
    """At 8 fps the 250 ms window is exactly two frames (a longer one would take three); one frame pair
    is a sequence too."""
    from noisebase.metrics.fvvdp import nb_fvvdp

    test, ref = _pair(frames, 32, 40, seed=7)
    out, reference = [nbp.to_unit(f) for f in test], [nbp.to_unit(f) for f in ref]
    feeder = nb_fvvdp(display_name="standard_fhd").video_feeder(32, 40, frames, fps)
    for t, r in zip(out, reference, strict=True):
        feeder.feed(t, r)
    assert nbp.fovvideovdp(out, reference, fps=fps) == pytest.approx(feeder.compute(), abs=1e-6)


def test_the_frame_rate_reaches_fovvideovdp_through_score_sequence_and_nothing_is_printed(capsys):
    test, ref = _pair(4, 32, 40, seed=8)
    out, reference = [nbp.to_unit(f) for f in test], [nbp.to_unit(f) for f in ref]
    nbp.fovvideovdp(out, reference)  # the first call imports pyfvvdp (which may warn)
    capsys.readouterr()
    at_8 = nbp.score_sequence(test, ref, warmup=0, fps=8.0)["fvvdp"]
    assert at_8 == pytest.approx(nbp.fovvideovdp(out, reference, fps=8.0), abs=1e-9)
    assert abs(at_8 - nbp.score_sequence(test, ref, warmup=0)["fvvdp"]) > 1e-4  # 30 fps reads otherwise
    assert capsys.readouterr() == ("", "")  # quiet: an evaluation's log stays one line per sequence


def test_sequences_of_unequal_length_are_one_line_errors_for_the_temporal_metrics():
    test, ref = _pair(3, 24, 32)
    out, reference = [nbp.to_unit(f) for f in test], [nbp.to_unit(f) for f in ref]
    for call in (
        lambda: nbp.temporal(nbp.psnr, out, reference[:2]),
        lambda: nbp.fovvideovdp(out, reference[:2]),
    ):
        with pytest.raises(DataError) as excinfo:
            call()
        one_line_error(excinfo, "3 and 2")
    with pytest.raises(DataError) as excinfo:  # one frame has no pair to difference
        nbp.temporal(nbp.psnr, out[:1], reference[:1])
    one_line_error(excinfo, "1 and 1")


def _their_sequence(theirs, test, ref, warmup):
    """Their `main()` loop for one sequence, minus the PNG reading and the 'cuda' moves."""
    from noisebase.metrics.flip import flip
    from noisebase.metrics.fvvdp import nb_fvvdp

    n = test.shape[0] - warmup
    fvvdp = nb_fvvdp(display_name="standard_fhd").video_feeder(test.shape[1], test.shape[2], n, 30)
    tpsnr, trmae = theirs.TemporalMetricAdapter(theirs.psnr), theirs.TemporalMetricAdapter(theirs.rmae)
    sums = dict.fromkeys(("mse", "psnr", "ssim", "msssim", "flip"), 0.0)
    for t_u8, r_u8 in zip(test[warmup:], ref[warmup:], strict=True):
        r, t = theirs.np_to_torch(r_u8), theirs.np_to_torch(t_u8)
        fvvdp.feed(t, r)
        tpsnr.feed(t, r)
        trmae.feed(t, r)
        for key in ("mse", "psnr", "ssim", "msssim"):
            sums[key] += getattr(theirs, key)(t, r)
        sums["flip"] += flip(t, r)
    return {"fvvdp": fvvdp.compute(), "tpsnr": tpsnr.compute(), "trmae": trmae.compute()} | {
        k: v / n for k, v in sums.items()
    }


def test_score_sequence_equals_their_script(theirs):
    test, ref = _pair(19, seed=6)
    expected = _their_sequence(theirs, test, ref, warmup=16)
    ours = nbp.score_sequence(test, ref, warmup=16)
    assert set(nbp.METRICS) <= set(ours)
    for key in nbp.METRICS:
        assert ours[key] == pytest.approx(expected[key], abs=1e-6), key
    assert ours["frames"] == 3 and ours["warmup"] == 16


def test_identical_frames_closed_forms(theirs):
    _, ref = _pair(3, seed=7)
    r = [nbp.to_unit(f) for f in ref]
    with pytest.raises(ZeroDivisionError):  # their script stops there; ours reports +inf
        theirs.psnr(r[0], r[0])
    assert nbp.psnr(r[0], r[0]) == math.inf
    assert nbp.mse(r[0], r[0]) == 0.0 and nbp.rmae(r[0], r[0]) == 0.0
    assert nbp.ssim(r[0], r[0]) == pytest.approx(1.0, abs=1e-6)
    assert nbp.msssim(r[0], r[0]) == pytest.approx(1.0, abs=1e-6)
    assert nbp.flip(r[0], r[0]) == pytest.approx(0.0, abs=1e-6)
    assert nbp.temporal(nbp.psnr, r, r) == math.inf
    scores = nbp.score_sequence(ref, ref, warmup=0, use_fvvdp=False)
    assert scores["psnr"] == math.inf and scores["tpsnr"] == math.inf and scores["fvvdp"] is None


def test_psnr_by_value():
    # Every channel off by 0.1: mse 0.01, 20 dB; rMAE of 0.1 against a reference of 0.5: 0.1 / 0.51 / 3.
    ref = torch.full((1, 3, 4, 4), 0.5)
    assert nbp.mse(ref + 0.1, ref) == pytest.approx(0.01, rel=1e-5)
    assert nbp.psnr(ref + 0.1, ref) == pytest.approx(20.0, abs=1e-4)
    assert nbp.rmae(ref + 0.1, ref) == pytest.approx(0.1 / 0.51 / 3, rel=1e-5)
    # Luminance: (x ** 2.2) weighted 0.2126, 0.7152, 0.0722.
    rgb = torch.tensor([1.0, 0.5, 0.0]).view(1, 3, 1, 1)
    assert float(nbp.luminance(rgb)) == pytest.approx(0.2126 + 0.7152 * 0.5**2.2, rel=1e-6)


def test_warmup_drops_the_first_16_frames():
    test, ref = _pair(19, 24, 32, seed=8)
    garbage = test.copy()
    garbage[:16] = np.random.default_rng(9).integers(0, 256, garbage[:16].shape, dtype=np.uint8)
    kept = nbp.score_sequence(garbage, ref, use_fvvdp=False)  # warmup 16, the default
    tail = nbp.score_sequence(test[16:], ref[16:], warmup=0, use_fvvdp=False)
    assert kept["warmup"] == 16 and kept["frames"] == 3
    for key in ("tpsnr", "trmae", "mse", "psnr", "ssim", "flip"):
        assert kept[key] == tail[key], key
    everything = nbp.score_sequence(garbage, ref, warmup=0, use_fvvdp=False)
    assert everything["psnr"] < kept["psnr"] - 3  # the garbage would have counted
    assert kept["msssim"] is None  # 24-pixel frames: below MS-SSIM's five scales


def test_bad_sequences_are_one_line_errors():
    test, ref = _pair(17, 24, 32)
    with pytest.raises(DataError) as excinfo:
        nbp.score_sequence(test, ref, warmup=16, use_fvvdp=False)
    one_line_error(excinfo, "metrics.noisebase.warmup=16", "17 frames")
    with pytest.raises(DataError) as excinfo:
        nbp.score_sequence(test.astype(np.float32), ref, warmup=0, use_fvvdp=False)
    one_line_error(excinfo, "uint8", "float32")
    with pytest.raises(DataError) as excinfo:  # the same rank, another width
        nbp.score_sequence(test, ref[:, :, :-1], warmup=0, use_fvvdp=False)
    one_line_error(excinfo, "(17, 24, 32, 3)", "(17, 24, 31, 3)")
    four = np.concatenate([test, test[..., :1]], -1)  # four channels, rank right
    with pytest.raises(DataError) as excinfo:
        nbp.score_sequence(four, np.concatenate([ref, ref[..., :1]], -1), warmup=0, use_fvvdp=False)
    one_line_error(excinfo, "(17, 24, 32, 4)")
    with pytest.raises(DataError) as excinfo:
        nbp.msssim(nbp.to_unit(test[0]), nbp.to_unit(ref[0]))
    one_line_error(excinfo, "MS-SSIM", "24 pixels", "161")


@pytest.mark.parametrize("side", [nbp.MSSSIM_MIN_SIDE - 1, nbp.MSSSIM_MIN_SIDE])
def test_msssim_is_scored_from_its_minimum_side_and_left_out_one_pixel_below(side):
    test, ref = _pair(2, side, side + 3, noise=20)
    scores = nbp.score_sequence(test, ref, warmup=0, use_fvvdp=False)
    if side < nbp.MSSSIM_MIN_SIDE:
        assert scores["msssim"] is None
        with pytest.raises(DataError) as excinfo:
            nbp.msssim(nbp.to_unit(test[0]), nbp.to_unit(ref[0]))
        one_line_error(excinfo, f"{side} pixels")
        return
    import pytorch_msssim

    def lum(x):  # Rec. 709 weights of the PNG values to the power 2.2, written out here
        lin = (torch.as_tensor(x, dtype=torch.float64) / 255) ** 2.2
        return (lin @ torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64))[None, None].float()

    want = np.mean(
        [
            float(pytorch_msssim.ms_ssim(lum(t), lum(r), data_range=1.0))
            for t, r in zip(test, ref, strict=True)
        ]
    )
    assert scores["msssim"] == pytest.approx(want, rel=1e-5) and 0 < scores["msssim"] < 1


@pytest.mark.parametrize(("warmup", "ok"), [(-1, False), (0, True), (3, True), (4, False)])
def test_the_warmup_may_leave_exactly_two_frames_and_not_fewer(warmup, ok):
    test, ref = _pair(5, 24, 32)
    if ok:
        assert nbp.score_sequence(test, ref, warmup=warmup, use_fvvdp=False)["frames"] == 5 - warmup
        return
    with pytest.raises(DataError) as excinfo:
        nbp.score_sequence(test, ref, warmup=warmup, use_fvvdp=False)
    one_line_error(excinfo, f"metrics.noisebase.warmup={warmup}", "5 frames")


def test_versions_recorded_and_pyfvvdp_shim():
    found = nbp.versions()
    assert set(found) == set(nbp.PACKAGES)
    assert found == {name: importlib.metadata.version(name) for name in nbp.PACKAGES}
    assert found["pyfvvdp"] == "1.2.0" and found["noisebase"] == "1.1.1"
    fvvdp = nbp.import_pyfvvdp()
    assert fvvdp.__name__ == "fvvdp"
    shape_base = sys.modules["numpy.lib.shape_base"]
    assert shape_base.expand_dims is np.expand_dims  # the one name pyfvvdp takes from it


# -- the sequence evaluation with metrics.protocol=noisebase ------------------------------------------------
def _protocol_eval(vol_data, tmp_path, monkeypatch, *overrides):
    """(summary, logged metrics, per_image rows, tags) of the stubbed evaluation (tests/sequence_eval_stub.py)
    with the Noisebase protocol, 1 warm-up frame."""
    protocol = ["metrics.protocol=noisebase", "metrics.noisebase.warmup=1"]
    run = stub_sequence_eval(vol_data, tmp_path, monkeypatch, [*protocol, *overrides])
    return run.summary, run.logged, run.rows, run.tags


def test_the_sequence_evaluation_scores_each_sequence_with_the_protocol(vol_data, tmp_path, monkeypatch):
    summary, logged, rows, tags = _protocol_eval(vol_data, tmp_path, monkeypatch)
    assert len(rows) == 2
    for row in rows.itertuples():
        reference = np.stack([synthetic_frame(row.scene, f, max(SPPS))["color"] for f in range(4)])
        denoised = reference * SCALES.numpy().reshape(4, 1, 1, 1)
        expected = nbp.score_sequence(
            np.stack([nbp.srgb8(f) for f in denoised]), np.stack([nbp.srgb8(f) for f in reference]), warmup=1
        )
        for key in ("psnr", "ssim", "flip", "mse", "tpsnr", "trmae", "fvvdp"):
            assert getattr(row, f"nb_{key}") == pytest.approx(expected[key], rel=1e-6, abs=1e-9), key
            assert logged[f"eval_nb_{key}_spp{row.spp}"] == pytest.approx(
                getattr(row, f"nb_{key}"), rel=1e-12
            )
        assert "nb_msssim" not in rows  # frames under 161 pixels: left out, never faked
        saved = json.loads(
            (tmp_path / "eval" / "noisebase" / f"{row.scene}-{row.spp:05d}spp.json").read_text()
        )
        assert saved["psnr"] == pytest.approx(row.nb_psnr, rel=1e-12) and saved["warmup"] == 1
        assert saved["versions"] == nbp.versions() and saved["frames"] == 3
    assert (rows["nb_psnr"] != rows["psnr"]).all()  # 8-bit ACES frames, not metrics.tonemap
    header = json.loads((tmp_path / "eval" / "metrics.json").read_text())["noisebase_protocol"]
    assert header == {"warmup": 1, "fvvdp": True, "versions": nbp.versions()}
    assert tags["nrbench.noisebase.pyfvvdp"] == "1.2.0" and tags["nrbench.noisebase.fvvdp"] == "true"
    assert summary["mean"]["nb_fvvdp"] == pytest.approx(rows["nb_fvvdp"].mean(), rel=1e-12)


def test_an_undefined_output_frame_has_no_protocol_numbers_and_writes_no_file(
    vol_data, tmp_path, monkeypatch
):
    """The protocol meets an undefined output (a GP expression's NaN weights): the sequence's nb_ scores
    are NaN (its 8-bit frames would hide the NaN), the other sequence is scored as usual."""
    protocol = ["metrics.protocol=noisebase", "metrics.noisebase.warmup=1", "metrics.noisebase.fvvdp=false"]
    run = stub_sequence_eval(vol_data, tmp_path, monkeypatch, protocol, undefined_spp=min(SPPS))
    rows = run.rows
    bad, good = rows[rows.spp == min(SPPS)].iloc[0], rows[rows.spp != min(SPPS)].iloc[0]
    assert bad["undefined"] > 0 and np.isnan(bad["nb_psnr"]) and np.isnan(bad["nb_flip"])
    assert np.isfinite(good["nb_psnr"]) and good["undefined"] == 0
    # the same columns as a defined sequence's: no fvvdp (left out), no msssim (frames under 161 pixels)
    assert "nb_fvvdp" not in rows and "nb_msssim" not in rows
    assert np.isnan(run.logged[f"eval_nb_psnr_spp{min(SPPS)}"])
    assert run.logged["eval_nb_psnr"] == pytest.approx(good["nb_psnr"], rel=1e-12)
    saved = {p.name for p in (tmp_path / "eval" / "noisebase").glob("*.json")}
    assert saved == {f"{good['scene']}-{good['spp']:05d}spp.json"}


def test_fvvdp_can_be_left_out_and_the_warmup_must_leave_two_frames(vol_data, tmp_path, monkeypatch):
    _, logged, rows, tags = _protocol_eval(
        vol_data, tmp_path / "a", monkeypatch, "metrics.noisebase.fvvdp=false"
    )
    assert "nb_fvvdp" not in rows and "nb_psnr" in rows
    assert not any("nb_fvvdp" in k for k in logged) and tags["nrbench.noisebase.fvvdp"] == "false"
    with pytest.raises(DataError) as excinfo:
        _protocol_eval(vol_data, tmp_path / "b", monkeypatch, "metrics.noisebase.warmup=3")
    one_line_error(excinfo, "metrics.noisebase.warmup=3", "4 frames")


def test_the_protocol_on_still_images_is_a_one_line_config_error(tmp_path):
    cfg = smoke_config(tmp_path, tmp_path, ["model=cross_bilateral", "metrics.protocol=noisebase"])
    with pytest.raises(ConfigError) as excinfo:
        validate_run(cfg)  # at job start, before any training
    one_line_error(excinfo, "metrics.protocol=noisebase", "dataset=procedural", "still images")


# -- the Noisebase table ------------------------------------------------------------------------------------
def _runs(**extra) -> pd.DataFrame:
    """Three runs: model a (two seeds) and b at 4 and 8 spp, a's FVVDP left out in one seed."""
    rows = [
        {"params.model.name": "a", "metrics.eval_nb_psnr_spp4": 20.0, "metrics.eval_nb_fvvdp_spp4": 6.0},
        {"params.model.name": "a", "metrics.eval_nb_psnr_spp4": 22.0},
        {"params.model.name": "b", "metrics.eval_nb_psnr_spp4": 25.0, "metrics.eval_nb_fvvdp_spp4": 5.0},
    ]
    for row, psnr8 in zip(rows, (30.0, 32.0, 28.0), strict=True):
        row |= {"metrics.eval_nb_psnr_spp8": psnr8, "metrics.eval_nb_ssim_spp8": psnr8 / 100}
        row |= {"metrics.eval_psnr": 1.0, "tags.nrbench.noisebase.pyfvvdp": "1.2.0"}
        row |= {"params.metrics.noisebase.warmup": "16"} | extra
    rows[1]["tags.nrbench.noisebase.fvvdp"] = "false"
    return pd.DataFrame(rows)


def test_the_noisebase_table_keeps_published_rows_apart():
    table = noisebase_table(_runs())
    frame = table.reset_index()
    measured = frame[frame["source"] == "measured"]
    assert list(zip(measured["model"], measured["spp"], strict=True)) == [
        ("a", 4),
        ("b", 4),
        ("a", 8),
        ("b", 8),
    ]
    assert measured["PSNR"].tolist() == [21.0, 25.0, 31.0, 28.0]  # mean over a's two seeds
    assert measured["runs"].tolist() == [2, 1, 2, 1]
    assert measured["FVVDP"].iloc[:2].tolist() == [6.0, 5.0]  # only the seed that computed it
    published = frame[frame["source"] == "published"].iloc[0]
    assert (published["spp"], published["PSNR"], published["SSIM"], published["FVVDP"]) == (
        4,
        29.35,
        0.883,
        7.66,
    )
    assert math.isnan(published["FLIP"]) and published["runs"] == 0
    # Best per spp among measured rows only: b at 4 spp (25 < the published 29.35), a at 8 spp.
    best = best_measured(table)
    assert best["PSNR"] == {1, 2} and best["FVVDP"] == {0}
    notes = " ".join(table.attrs["notes"])
    assert "pyfvvdp 1.2.0" in notes and "FVVDP left out" in notes and "first 16 frames" in notes
    assert "Balint et al. 2023" in notes and "cvvdp" in notes
    markdown = to_markdown(table, best)
    assert "| published | NPPD (Balint et al. 2023, test8) | 4 | 29.35 | 0.8830 |" in markdown
    assert "**25.00**" in markdown and "**29.35**" not in markdown


def test_no_noisebase_table_without_protocol_runs():
    runs = _runs().drop(columns=[c for c in _runs().columns if "eval_nb_" in c])
    assert noisebase_table(runs) is None


@pytest.mark.slow
def test_the_smoke_pipeline_with_the_protocol_writes_the_noisebase_table(tmp_path):
    """render -> preprocess -> eval -> report on a Noisebase fixture set through `python -m src.run`."""
    import os
    import subprocess

    from tests.conftest import ROOT
    from tests.noisebase_fixture import write_training_sequence

    for i in range(3):
        write_training_sequence(
            tmp_path / "nb" / "train" / f"scene{i:04d}.zip", frames=2, size=16, spp=8, seed=i
        )  # 8 stored samples: the smoke profile's ladder reaches 8
    env = os.environ | {
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path}/mlflow.db",
        "NRBENCH_DATA_DIR": str(tmp_path / "data"),
        "OMP_NUM_THREADS": "1",
    }
    command = [sys.executable, "-m", "src.run", "dataset=noisebase", f"dataset.root={tmp_path}/nb"]
    command += ["profile=smoke", "dataset.files='train/scene{index:04d}.zip'", "dataset.rendering_height=64"]
    command += ["dataset.rendering_width=96", "dataset.crop=null", f"hydra.run.dir={tmp_path}/run"]
    command += [f"tracking.artifact_root={tmp_path}/art", f"report.name={tmp_path}/report", "stage=all"]
    command += ["model=cross_bilateral", "metrics.protocol=noisebase", "metrics.noisebase.warmup=0"]
    command += [
        "dataset.volume_features=[color,color.var,albedo,albedo.var,normal,normal.var,depth,depth.var]"
    ]
    result = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, (result.stdout + result.stderr)[-3000:]
    rows = pd.read_csv(tmp_path / "run" / "eval" / "per_image.csv")
    table = (tmp_path / "report" / "noisebase.md").read_text()
    for row in rows.itertuples():
        assert (
            f"| measured | cross_bilateral | {row.spp} | {row.nb_psnr:.2f} |" in table
        )  # one sequence per spp
    assert "| published | NPPD (Balint et al. 2023, test8) | 4 | 29.35 |" in table
    assert "pyfvvdp 1.2.0" in table and "first 0 frames" in table
    assert "Noisebase protocol" in (tmp_path / "report" / "index.html").read_text()
    # the protocol and the spp-equivalent meet: an equivalent from the stored samples, no speed-up (no render
    # time), and the samples-saved table says so
    assert rows["spp_equivalent"].notna().all() and rows["noisy_spp_equivalent"].gt(0).all()
    assert rows["speedup"].isna().all() and rows["render_s_per_spp"].isna().all()
    saved = pd.read_csv(tmp_path / "report" / "samples_saved.csv", comment="#")
    assert len(saved) == 2 and saved["speed-up"].isna().all() and saved["spp-equivalent"].gt(0).all()


# Mutation testing (scripts/mutation.sh noisebase_protocol): the mutants left alive are equivalent here:
# - every `device=` dropped or set to None, and `to_unit` without its dtype or device: the CPU either way
#   (and to_unit's frames are uint8, which `/ 255` makes float32 too); a GPU run of the protocol is what
#   scripts/device_check.sh is for;
# - `zip(..., strict=...)` weakened: both sequences' lengths are checked before every zip;
# - `luminance`'s `x[:, 2:4]`, `msssim`'s and `fovvideovdp`'s `shape[+2:]`, `float("INF")`: the same values
#   on (N, 3, H, W) tensors;
# - FovVideoVDP's foveation inputs (`centre` and the first argument of `process_block_of_frames`), the
#   band frequencies passed to `do_pooling_and_jods`, `temp_padding`, `use_checkpoints`, `quiet`,
#   `foveated=None`, `color_space` and the pyramid choice (`local_adapt` is "gpyr" in pyfvvdp 1.2.0):
#   pyfvvdp reads them only in foveated mode, in its own `predict_video_source` (whose padding and
#   printing the stream replaces), or they equal its defaults; the parity with Noisebase's feeder
#   (at 30 and 8 fps, on 1 and 5 frames) pins the number;
# - `channels` with a batch of 2 or a fifth channel: the block reads channels 0-3 of each batch entry and
#   the pooling's mean of two identical entries is the entry;
# - `250.0 / (1001.0 / fps)`: the same window length at every frame rate where 250 ms x fps / 1000 is not
#   within 0.1 % above an integer (30 and 8 fps among them);
# - the pyfvvdp shim's module names (`import_own`'s package, the `numpy.lib.shape_base` key): pyfvvdp is
#   imported once per process, before which nothing else registers the name.
