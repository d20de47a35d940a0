"""`python -m src.bench filter`: the GP search's fitness throughput and the per-frame filtering time."""

from __future__ import annotations

import re

import pytest

from src.bench.cli import main as bench_main

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
