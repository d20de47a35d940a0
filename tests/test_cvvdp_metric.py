"""ColorVideoVDP (`metrics.cvvdp`, src/metrics/cvvdp_metric.py): the wrapper against the `cvvdp` package's
own API called here on the same frames, the metric's fixed points and ordering on small moving sequences,
its config checks, and the sequence evaluation's `cvvdp` / `noisy_cvvdp` columns, tag and metrics.json
entry. Frames are small (non-square, so a swapped height and width changes the number) and few."""

from __future__ import annotations

import importlib.metadata

import numpy as np
import pandas as pd
import pytest
import torch

from src.errors import ConfigError, DataError
from src.metrics.cvvdp_metric import (
    JOD_MAX,
    check_display,
    cvvdp_jod,
    display_encoded,
    display_names,
    version,
)
from src.metrics.image import tonemap
from src.schema.run import validate_run
from tests.conftest import one_line_error, smoke_config
from tests.sequence_eval_stub import stub_frames, stub_sequence_eval
from tests.test_volume_shards import SPPS

F, H, W = 6, 24, 20


def _moving(frames=F, seed=0):
    """A linear HDR sequence (F, H, W, 3) whose content moves: a colour grating drifting one pixel per frame
    over a fixed random texture, values in [0.05, 1.3] (some above 1, clipped by the tone map)."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[:H, :W].astype(np.float64)
    texture = rng.uniform(0.0, 0.3, (H, W, 3))
    out = []
    for f in range(frames):
        phase = 2 * np.pi * (cols - f) / 7.0
        grating = np.stack([np.sin(phase), np.sin(phase + 2.0), np.cos(phase + rows / 5)], axis=-1)
        out.append(0.05 + 0.5 * (1 + grating) + texture)
    return np.stack(out)


def _noisy(reference, sigma, seed=1):
    return np.maximum(reference + np.random.default_rng(seed).normal(0, sigma, reference.shape), 0.0)


def _direct(test, reference, display="standard_fhd", fps=30.0, tone=lambda x: np.clip(x, 0, 1) ** (1 / 2.2)):
    """The package's own API, as its README calls it, on frames tone-mapped here by hand."""
    import pycvvdp

    metric = pycvvdp.cvvdp(display_name=display, device=torch.device("cpu"), quiet=True)
    jod, _ = metric.predict(
        tone(test).astype(np.float32),
        tone(reference).astype(np.float32),
        dim_order="FHWC",
        frames_per_second=fps,
    )
    return float(jod)


def _reinhard(x):
    x = np.maximum(x, 0.0)
    return (x / (1 + x)) ** (1 / 2.2)


@pytest.mark.parametrize(
    ("kwargs", "direct"),
    [
        ({}, {}),
        (
            {"display": "sdr_fhd_24", "fps": 24.0, "method": "reinhard_gamma"},
            {"display": "sdr_fhd_24", "fps": 24.0, "tone": _reinhard},
        ),
    ],
    ids=["defaults", "display-fps-tonemap"],
)
def test_the_wrapper_equals_the_packages_own_call_on_the_same_frames(kwargs, direct):
    reference = _moving()
    test = _noisy(reference, 0.05)
    ours = cvvdp_jod(test, reference, **kwargs)
    assert ours == pytest.approx(_direct(test, reference, **direct), abs=1e-6)
    assert ours < JOD_MAX - 0.1  # the fixture is not at the metric's ceiling, where any order agrees


def test_the_settings_reach_the_metric():
    """Each of display, fps and tone map changes the number (else the parity above could not tell)."""
    reference = _moving()
    test = _noisy(reference, 0.05)
    base = cvvdp_jod(test, reference)
    for kwargs in ({"display": "standard_4k"}, {"fps": 60.0}, {"method": "reinhard_gamma"}):
        assert abs(cvvdp_jod(test, reference, **kwargs) - base) > 1e-3, kwargs


def test_the_reference_against_itself_scores_the_maximum_and_the_number_is_deterministic():
    reference = _moving()
    assert cvvdp_jod(reference, reference) == pytest.approx(JOD_MAX, abs=1e-6)
    test = _noisy(reference, 0.05)
    assert cvvdp_jod(test, reference) == cvvdp_jod(test.copy(), reference.copy())


def test_more_noise_scores_lower():
    reference = _moving()
    scores = [cvvdp_jod(_noisy(reference, sigma), reference) for sigma in (0.01, 0.04, 0.16)]
    assert scores[0] > scores[1] + 0.1 > scores[2] + 0.2, scores


def test_a_frozen_first_frame_scores_below_the_true_sequence():
    reference = _moving()
    frozen = np.repeat(reference[:1], F, axis=0)
    assert cvvdp_jod(reference, reference) - cvvdp_jod(frozen, reference) > 0.5


def test_undefined_or_mismatched_frames_are_one_line_data_errors():
    reference = _moving()
    bad = reference.copy()
    bad[2, 3, 4, 1] = np.nan
    with pytest.raises(DataError) as excinfo:
        cvvdp_jod(bad, reference)
    one_line_error(excinfo, "cvvdp", "1 NaN/Inf")
    with pytest.raises(DataError) as excinfo:
        cvvdp_jod(reference[:, :, :-1], reference)
    one_line_error(excinfo, "cvvdp", "shapes differ")


def test_the_shape_error_names_both_shapes_and_the_frame_layout_is_checked_on_each_axis():
    reference = _moving()
    with pytest.raises(DataError) as excinfo:
        cvvdp_jod(reference[:, :, :-1], reference)
    one_line_error(excinfo, f"denoised {(F, H, W - 1, 3)} vs reference {(F, H, W, 3)}")
    for bad in (reference[0], np.concatenate([reference, reference[..., :1]], -1)):  # (H, W, 3); 4 channels
        with pytest.raises(DataError) as excinfo:
            display_encoded(bad, "clip_gamma", 2.2)
        one_line_error(excinfo, "expected frames of shape (F, H, W, 3)", str(bad.shape))


def test_the_frame_rate_must_be_positive_and_a_slow_one_is_accepted():
    reference = _moving(frames=3)
    for fps in (0.0, -1.0):
        with pytest.raises(ConfigError) as excinfo:
            cvvdp_jod(reference, reference, fps=fps)
        one_line_error(excinfo, f"metrics.cvvdp.fps={fps!r}")
    assert cvvdp_jod(reference, reference, fps=0.5) == pytest.approx(JOD_MAX, abs=1e-3)  # 0 < fps <= 1


def test_the_gamma_reaches_the_display_encoding_and_the_score():
    frames = _moving(frames=3)
    for gamma in (2.2, 1.6):
        want = np.stack([tonemap(f, "clip_gamma", gamma) for f in frames]).astype(np.float32)
        np.testing.assert_array_equal(display_encoded(frames, "clip_gamma", gamma), want)
    noisy = np.clip(frames + np.random.default_rng(3).normal(0, 0.05, frames.shape), 0, None)
    assert cvvdp_jod(noisy, frames, gamma=1.6) != pytest.approx(cvvdp_jod(noisy, frames), abs=1e-4)


def test_the_metric_prints_nothing(capsys):
    reference = _moving(frames=3)
    cvvdp_jod(reference, reference)  # the first call imports the package (whose import may warn)
    capsys.readouterr()
    cvvdp_jod(reference, reference)
    # quiet=True: no progress bar per sequence in an evaluation's log
    assert capsys.readouterr() == ("", "")


def test_the_known_displays_are_the_packages_sdr_models():
    names = display_names()
    assert {"standard_fhd", "standard_4k", "sdr_fhd_24"} <= set(names)
    assert not any(n.startswith(("standard_hdr", "65inch_hdr")) for n in names)  # PQ / HLG / linear input
    assert check_display("standard_fhd") == "standard_fhd"
    with pytest.raises(ConfigError) as excinfo:
        check_display("standard_hdr_pq")
    one_line_error(excinfo, "metrics.cvvdp.display='standard_hdr_pq'", "standard_fhd", "sdr_fhd_24")
    assert version() == importlib.metadata.version("cvvdp") == "0.5.7"


# -- the config ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("overrides", "needles"),
    [
        (["metrics.cvvdp.display=standard_fdh"], ["metrics.cvvdp.display='standard_fdh'", "standard_fhd"]),
        (["metrics.cvvdp.fps=0"], ["metrics.cvvdp.fps=0: expected a positive number"]),
        (["metrics.cvvdp.enabled=yes"], ["metrics.cvvdp.enabled='yes': expected true or false"]),
        (
            ["metrics.cvvdp.enabled=true"],  # the default dataset: still images
            ["metrics.cvvdp.enabled=true", "sequences only", "dataset=procedural"],
        ),
    ],
)
def test_a_bad_cvvdp_setting_is_a_one_line_config_error(overrides, needles, tmp_path):
    cfg = smoke_config(tmp_path, tmp_path / "run", overrides)
    with pytest.raises(ConfigError) as excinfo:
        validate_run(cfg)
    one_line_error(excinfo, *needles)


def test_cvvdp_on_sequences_passes_the_schema(tmp_path):
    overrides = ["dataset=volumetric", "metrics.cvvdp.enabled=true", "metrics.cvvdp.fps=24"]
    cfg = smoke_config(tmp_path, tmp_path / "run", overrides)
    assert validate_run(cfg)["metrics"]["cvvdp"] == {"enabled": True, "display": "standard_fhd", "fps": 24}


@pytest.mark.slow
def test_the_cli_exits_2_on_a_wrong_display(tmp_path):
    from tests.conftest import one_line_cli_error
    from tests.test_bad_inputs import run_cli

    result = run_cli(["dataset=volumetric", "metrics.cvvdp.display=nope"], tmp_path / "data")
    one_line_cli_error(result, "metrics.cvvdp.display='nope'", "standard_fhd")


# -- the sequence evaluation --------------------------------------------------------------------------------
def _evaluate(vol_data, out, monkeypatch, overrides=(), undefined_spp=None):
    """The stubbed evaluation (tests/sequence_eval_stub.py) with the reinhard_gamma tone map."""
    tonemap = ["metrics.tonemap=reinhard_gamma"]
    return stub_sequence_eval(vol_data, out, monkeypatch, [*tonemap, *overrides], undefined_spp)


def test_the_sequence_evaluation_scores_each_sequence_and_records_the_version(
    vol_data, tmp_path, monkeypatch
):
    run = _evaluate(vol_data, tmp_path, monkeypatch, ["metrics.cvvdp.enabled=true", "metrics.cvvdp.fps=24"])
    summary, logged, rows, header, tags = run.summary, run.logged, run.rows, run.header, run.tags
    assert len(rows) == 2
    for row in rows.itertuples():
        denoised, noisy, reference, _ = stub_frames(row)
        options = {"display": "standard_fhd", "fps": 24.0, "method": "reinhard_gamma"}
        assert row.cvvdp == pytest.approx(cvvdp_jod(denoised, reference, **options), abs=1e-6)
        assert row.noisy_cvvdp == pytest.approx(cvvdp_jod(noisy, reference, **options), abs=1e-6)
        assert logged[f"eval_cvvdp_spp{row.spp}"] == pytest.approx(row.cvvdp, abs=1e-6)
        assert logged[f"eval_noisy_cvvdp_spp{row.spp}"] == pytest.approx(row.noisy_cvvdp, abs=1e-6)
    assert (rows["cvvdp"] != rows["noisy_cvvdp"]).all() and (rows["cvvdp"] < JOD_MAX - 0.1).all()
    assert logged["eval_cvvdp"] == pytest.approx(rows["cvvdp"].mean(), abs=1e-6)
    assert summary["mean"]["noisy_cvvdp"] == pytest.approx(rows["noisy_cvvdp"].mean(), abs=1e-6)
    assert header["cvvdp"] == {"display": "standard_fhd", "fps": 24.0, "version": "0.5.7"}
    assert tags == {"nrbench.cvvdp.version": "0.5.7"}


def test_disabled_there_is_no_cvvdp_column_tag_or_header(vol_data, tmp_path, monkeypatch):
    run = _evaluate(vol_data, tmp_path, monkeypatch)
    summary, logged, rows, header, tags = run.summary, run.logged, run.rows, run.header, run.tags
    assert not any("cvvdp" in k for k in (*rows.columns, *logged, *summary["mean"], *header, *tags))
    assert "tpsnr" in rows  # the other sequence metrics are there


def test_an_item_with_an_undefined_frame_has_an_undefined_cvvdp(vol_data, tmp_path, monkeypatch):
    run = _evaluate(vol_data, tmp_path, monkeypatch, ["metrics.cvvdp.enabled=true"], undefined_spp=min(SPPS))
    logged, rows = run.logged, run.rows
    bad, good = rows[rows.spp == min(SPPS)].iloc[0], rows[rows.spp != min(SPPS)].iloc[0]
    assert np.isnan(bad.cvvdp) and np.isfinite(good.cvvdp)
    _, noisy, reference, _ = stub_frames(bad)
    expected = cvvdp_jod(noisy, reference, method="reinhard_gamma")
    assert bad.noisy_cvvdp == pytest.approx(expected, abs=1e-6)  # the input is still scored
    assert logged["eval_cvvdp"] == pytest.approx(good.cvvdp, abs=1e-6)  # the defined item's value
    assert np.isnan(logged[f"eval_cvvdp_spp{min(SPPS)}"])


# -- the tables ---------------------------------------------------------------------------------------------
def test_the_comparison_table_has_a_cvvdp_column_only_where_runs_log_it():
    from src.report.table_writers import best_rows
    from src.report.tables import NOISY_ROW, comparison_table

    runs = pd.DataFrame(
        [
            {"params.model.name": "a", "metrics.eval_psnr": 30.0, "metrics.eval_cvvdp": 8.0},
            {"params.model.name": "a", "metrics.eval_psnr": 31.0, "metrics.eval_cvvdp": 9.0},
            {"params.model.name": "b", "metrics.eval_psnr": 32.0, "metrics.eval_cvvdp": 7.0},
        ]
    ).assign(**{"metrics.eval_noisy_cvvdp": 5.0, "metrics.eval_cvvdp_spp4": [8.0, 9.0, 7.0]})
    table = comparison_table(runs, ["model.name"])
    assert table.loc["a", "CVVDP"] == 8.5 and table.loc["b", "CVVDP"] == 7.0
    assert table.loc[NOISY_ROW, "CVVDP"] == 5.0
    assert best_rows(table)["CVVDP"] == {1}  # higher is better: a (row 1, under the noisy row)
    assert "CVVDP 4spp" in comparison_table(runs, ["model.name"], group_by="spp")
    without = runs.drop(columns=[c for c in runs if "cvvdp" in c])
    assert "CVVDP" not in comparison_table(without, ["model.name"])


def _protocol_runs(cvvdp: bool) -> pd.DataFrame:
    """Two protocol runs (a, b) at 4 spp and one run without the protocol (c) that logged CVVDP only."""
    rows = [
        {"params.model.name": "a", "metrics.eval_nb_psnr_spp4": 20.0},
        {"params.model.name": "b", "metrics.eval_nb_psnr_spp4": 25.0},
        {"params.model.name": "c"},
    ]
    if cvvdp:
        for row, jod in zip(rows, (8.5, 7.5, 9.9), strict=True):
            row |= {"metrics.eval_cvvdp_spp4": jod, "tags.nrbench.cvvdp.version": "0.5.7"}
            row |= {"params.metrics.cvvdp.display": "standard_fhd", "params.metrics.cvvdp.fps": "30"}
    return pd.DataFrame(rows)


def test_the_noisebase_table_shows_cvvdp_as_an_optional_column_with_its_version():
    from src.report.noisebase_table import best_measured, noisebase_table

    table = noisebase_table(_protocol_runs(cvvdp=True))
    frame = table.reset_index()
    measured = frame[frame["source"] == "measured"]
    assert measured["model"].tolist() == ["a", "b"]  # c logged no protocol number: not a row
    assert measured["CVVDP"].tolist() == [8.5, 7.5]
    assert np.isnan(frame[frame["source"] == "published"].iloc[0]["CVVDP"])  # nothing published
    assert best_measured(table)["CVVDP"] == {0}
    note = next(n for n in table.attrs["notes"] if n.startswith("CVVDP"))
    assert "cvvdp 0.5.7" in note and "standard_fhd" in note and "30 fps" in note and "not a" in note

    without = noisebase_table(_protocol_runs(cvvdp=False))
    assert "CVVDP" not in without.columns and "CVVDP" not in without.attrs["metrics"]
    assert any("metrics.cvvdp.enabled=false" in n for n in without.attrs["notes"])


# Mutation testing (scripts/mutation.sh cvvdp): the mutants left alive are equivalent on a CPU:
# - `import_own("pycvvdp", <another name>)`: the package name only chooses whose top-level helpers come
#   first while pycvvdp is imported for the first time in a process; no other package with an `interp`
#   module is imported before it in the tests or the evaluation, so the same modules load;
# - `device=None` or no `device=`: pycvvdp then picks CUDA when there is one, else the CPU: the same device
#   on this machine (the evaluation passes its own device, tested on a GPU by scripts/device_check.sh);
# - `dim_order="fhwc"`: pycvvdp upper-cases the order (`video_source.reshuffle_dims`), and finds no batch
#   axis in either spelling.
