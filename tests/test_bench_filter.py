"""`python -m src.bench filter`: the GP search's fitness throughput and the per-frame filtering time."""

from __future__ import annotations

import re

import pytest

from src.bench.cli import _parser
from src.bench.cli import main as bench_main
from src.bench.filter import table41_rows

TINY = ["filter", "--width", "16", "--height", "12", "--islands", "1", "--population", "4", "--sample", "2"]
TINY += ["--radius", "1", "--device", "cpu", "--frame-width", "24", "--frame-height", "16"]


def test_filter_bench_prints_rates_and_a_frame_time_per_published_expression(capsys):
    assert bench_main(TINY) == 0
    out = capsys.readouterr().out
    rate = float(re.search(r"([\d.]+) expression evaluations/s", out).group(1))
    weights = float(re.search(r"([\d.]+) M weight evaluations/s", out).group(1))
    assert rate > 0
    assert weights == pytest.approx(rate * 16 * 12 * 9 / 1e6, rel=2e-3, abs=0.05)
    for name in ("gp_expr1", "gp_expr2", "gp_expr3"):
        assert re.search(rf"{name}: [\d.]+ s per frame", out)
    assert "one 24x16 frame, radius 1" in out


def test_filter_bench_frame_expressions_can_be_chosen_or_skipped(capsys):
    assert bench_main([*TINY, "--frame-expressions", "exp(-distance2(normal, normal))"]) == 0
    assert "exp(-distance2(normal, normal)): " in capsys.readouterr().out
    assert bench_main([*TINY, "--frame-expressions", ""]) == 0
    assert "per frame" not in capsys.readouterr().out
    assert bench_main([*TINY, "--frame-expressions", "gp_expr1;exp(-distance2(normal"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bench: --frame-expressions: cannot parse") and "\n" not in err


def test_filter_bench_bad_size_is_one_line_exit_2(capsys):
    assert bench_main([*TINY, "--frame-height", "0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bench: ") and "--frame-height must be >= 1" in err and "\n" not in err


def test_filter_bench_prints_the_thesis_table_41_numbers_from_the_one_mapping(capsys):
    assert bench_main(TINY) == 0
    assert "183.14 s on its GPU (CUDA), 27501.9 s on its CPU" in capsys.readouterr().out


# Davletaliyev 2016, Table 4.1 (seconds per iteration, GPU, CPU), typed here by hand, divided by its
# 4 x 50 = 200 expressions of one iteration (Sec. 4.1.2).
TABLE41_PER_EXPRESSION = {
    32: (0.002285, 0.013335),
    128: (0.033995, 3.673115),
    256: (0.11019, 15.8286),
    512: (0.9157, 137.5095),
}


def test_table41_rows_thesis_columns_are_table_4_1_over_200_and_ratios_ours_over_them():
    measured = {512: 3.0, 8: 0.5, 32: 0.01, 128: 0.2, 256: 1.5}  # made-up seconds per expression and image
    rows = table41_rows(measured, expressions=4)  # our population is not the thesis's 200
    assert [r.resolution for r in rows] == [512, 8, 32, 128, 256]
    for row in rows:
        assert row.ours == measured[row.resolution]
        assert row.iteration == pytest.approx(4 * measured[row.resolution])
        if row.resolution == 8:  # not in Table 4.1
            assert (row.thesis_gpu, row.thesis_cpu, row.ratio_gpu, row.ratio_cpu) == (None,) * 4
            continue
        gpu, cpu = TABLE41_PER_EXPRESSION[row.resolution]
        assert (row.thesis_gpu, row.thesis_cpu) == (pytest.approx(gpu), pytest.approx(cpu))
        assert row.ratio_gpu == pytest.approx(measured[row.resolution] / gpu)
        assert row.ratio_cpu == pytest.approx(measured[row.resolution] / cpu)
    assert table41_rows({512: 0.9157})[0].iteration == pytest.approx(183.14)  # default: the thesis's 200


TABLE = ["filter", "--table41", "--resolutions", "8,32", "--islands", "2", "--population", "2"]
TABLE += ["--sample", "2", "--radius", "1", "--device", "cpu", "--frame-expressions", ""]


def _table(out: str) -> dict[str, list[str]]:
    rows = [line.strip("|").split("|") for line in out.splitlines() if re.match(r"\| \d+x\d+ \|", line)]
    return {cells[0].strip(): [c.strip() for c in cells[1:]] for cells in rows}


def test_filter_bench_table41_prints_one_row_per_resolution_with_consistent_columns(capsys):
    assert bench_main(TABLE) == 0
    out = capsys.readouterr().out
    table = _table(out)
    assert list(table) == ["8x8", "32x32"]
    assert table["8x8"][1:5] == ["n/a"] * 4
    ours, gpu, cpu, ratio_gpu, ratio_cpu, iteration = table["32x32"]
    assert (float(gpu), float(cpu)) == (pytest.approx(0.002285, rel=5e-4), pytest.approx(0.013335, rel=5e-4))
    assert float(ratio_gpu) == pytest.approx(float(ours) / 0.002285, rel=2e-3)
    assert float(ratio_cpu) == pytest.approx(float(ours) / 0.013335, rel=2e-3)
    assert float(iteration) == pytest.approx(4 * float(ours), rel=2e-3)  # 2 x 2, every one counted
    assert "2 islands x 2 = 4 expressions (3 distinct" in out and "iteration of 4 |" in out
    assert "radius 1 (9 offsets)" in out and "does not state its filter radius (ours: 1)" in out
    assert re.search(
        r"timed 2 of the 3 distinct expressions at each resolution \(mean length [\d.]+ nodes\)", out
    )
    assert "the rest extrapolated" in out and "batched throughput" in out and "per frame" not in out
    assert bench_main([*TABLE, "--tree-batch", "1", "--resolutions", "8"]) == 0
    out = capsys.readouterr().out
    assert (
        list(_table(out)) == ["8x8"] and "one expression per call" in out and "batched throughput" not in out
    )


def test_filter_bench_table41_defaults_are_the_thesis_resolutions_and_4_x_50():
    args = _parser().parse_args(["filter", "--table41"])
    assert args.check(args) is None
    assert (args.resolutions, args.islands, args.population) == ([32, 128, 256, 512], 4, 50)
    args = _parser().parse_args(["filter"])
    assert args.check(args) is None
    assert (args.width, args.height, args.islands, args.population) == (512, 512, 4, 100)


@pytest.mark.parametrize(
    ("extra", "needles"),
    [
        (["--resolutions", "0,32"], ["--resolutions", "'0,32'", ">= 1"]),
        (["--resolutions", "-8"], ["--resolutions", "'-8'", ">= 1"]),
        (["--resolutions", ""], ["--resolutions", "''", ">= 1"]),
        (["--resolutions", "32,x"], ["--resolutions", "'32,x'", "sizes in pixels"]),
        (["--resolutions", "32,32"], ["--resolutions", "'32,32'", "distinct"]),
        (["--width", "64"], ["--width", "--table41"]),
        (["--images", "2"], ["--images", "one image", "found 2"]),
    ],
)
def test_filter_bench_table41_bad_input_is_one_line_exit_2(capsys, extra, needles):
    assert bench_main(["filter", "--table41", *extra]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("bench: ") and "\n" not in err
    for needle in needles:
        assert needle in err, (needle, err)


def test_filter_bench_resolutions_without_table41_is_one_line_exit_2(capsys):
    assert bench_main(["filter", "--resolutions", "32"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "bench: --resolutions applies only with --table41"


def test_filter_bench_table41_seconds_are_per_expression_of_the_timed_sample(capsys, monkeypatch):
    import src.bench.filter as bench_filter

    monkeypatch.setattr(bench_filter, "_timed", lambda fn, device: 0.5)  # the 2 sampled expressions: 0.5 s
    assert bench_main(TABLE) == 0
    ours, _, _, ratio_gpu, _, iteration = _table(capsys.readouterr().out)["32x32"]
    assert (float(ours), float(iteration)) == (0.25, 1.0)  # 0.5 s / 2 expressions; x 4 expressions
    assert float(ratio_gpu) == pytest.approx(0.25 / 0.002285, rel=1e-3)
