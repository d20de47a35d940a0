"""`python -m src.bench startup`: each command runs as a process in each checkout, its exit status and
first line are read back, the rounds time every command, and a bad argument is one line."""

import pytest

from src.bench.cli import main
from src.bench.startup import CASES, Outcome, selected_cases, startup_table
from src.errors import ConfigError
from tests.conftest import ROOT


def test_the_table_reports_each_commands_answer_in_each_checkout(capsys):
    # this checkout as both sides: the same commands, each run (1 warm-up + 2 rounds) per side
    assert (
        main(["startup", "--cases", "group_null,plus_existing", "--rounds", "2", "--before", str(ROOT)]) == 0
    )
    out = capsys.readouterr().out
    assert "2 rounds in a rotating order after 1 untimed" in out
    rows = [line for line in out.splitlines() if line.startswith("| config group") or line.startswith("| +")]
    assert len(rows) == 2
    for row in rows:
        cells = [c.strip() for c in row.strip("|").split("|")]
        assert len(cells) == 5  # command, then seconds and answer for before and after
        for seconds, answer in (cells[1:3], cells[3:5]):
            median = float(seconds.split()[0])
            assert 0 < median < 60
            assert answer.startswith("2, 1: `[nrbench][ERROR] - ")  # exit 2, one line printed
    assert "model=null: a config group takes one of its options" in rows[0]
    assert "+seed=3: seed is already in the config" in rows[1]


def test_the_table_shows_quartiles_and_truncates_long_lines():
    long = Outcome(status=1, lines=20, first_line="x" * 200, seconds=[1.0, 2.0, 3.0, 4.0, 5.0])
    table = startup_table(["model_typo"], {("after", "model_typo"): long}, ["after"])
    row = table.splitlines()[2]
    assert "| 3.00 [2.00, 4.00] | 1, 20: `" + "x" * 107 + "...` |" in row
    assert row.startswith("| misspelt model: `model=kpcnn` |")


def test_cases_are_chosen_by_id():
    assert selected_cases("all") == list(CASES)
    assert selected_cases("key_typo, accepted") == ["key_typo", "accepted"]
    with pytest.raises(ConfigError, match="--cases: unknown keytypo; expected some of model_typo"):
        selected_cases("keytypo")


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--rounds", "0"], "bench: --rounds must be >= 1, --warmup >= 0"),
        (["--warmup", "-1"], "bench: --rounds must be >= 1, --warmup >= 0"),
        (["--cases", "nope"], "bench: --cases: unknown nope"),
        (["--before", "/nonexistent"], "bench: --before /nonexistent: no src/run.py there"),
    ],
)
def test_a_bad_argument_is_one_line_and_status_2(argv, message, capsys):
    assert main(["startup", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith(message) and err.count("\n") == 1


def test_a_command_that_hangs_stops_the_bench_with_one_line(monkeypatch, capsys):
    from src.bench import startup

    monkeypatch.setattr(startup, "COMMAND_TIMEOUT_S", 0.01)  # no interpreter starts that fast
    assert main(["startup", "--cases", "model_typo", "--rounds", "1", "--warmup", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bench: python -m src.run model=kpcnn: no answer within 0.01 s in ")
    assert err.count("\n") == 1
