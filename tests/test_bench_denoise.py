"""`python -m src.bench denoise`: rounds in a rotating order, medians, spreads and per-round ratios, the
U-Net KPCN's claims against both KPCN forms and OIDN, conv depths, and the `--log` MLflow run."""

from __future__ import annotations

import csv
import itertools
import statistics
from collections import Counter
from pathlib import Path

import pytest
import torch

from src.bench.cli import main as bench_main
from src.bench.conv_depth import conv_depth, path_depth
from src.bench.denoise_table import format_claims, format_ratios, format_spreads
from src.bench.denoise_timing import Row, bench_config, timed_rows
from src.bench.timing import Rounds, Spread, ratio_spread, round_order, time_rounds
from src.models.instantiate import build_method

TINY = ["denoise", "--profile", "paper", "--width", "16", "--height", "12", "--device", "cpu"]


@pytest.mark.parametrize("n", [2, 3, 4, 5, 6, 7])
def test_each_round_runs_every_function_once_in_an_order_that_rotates(n):
    block = n if n % 2 == 0 else 2 * n  # a Williams design balances carry-over in n rounds, 2n for odd n
    orders = [round_order(n, r) for r in range(block)]
    assert all(sorted(order) == list(range(n)) for order in orders)
    assert all(a != b for a, b in itertools.pairwise(orders))
    # every function runs in every position equally often ...
    for position in range(n):
        assert Counter(order[position] for order in orders) == Counter({i: block // n for i in range(n)})
    # ... and directly after every other function equally often (never always after the same one)
    follows = Counter(pair for order in orders for pair in itertools.pairwise(order))
    assert follows == Counter({pair: block // n for pair in itertools.permutations(range(n), 2)})


class FakeClock:
    """A clock that a timed function advances by its scripted duration in each round."""

    def __init__(self, durations: dict[str, list[float]]) -> None:
        self.now, self.durations, self.calls = 0.0, durations, []

    def __call__(self) -> float:
        return self.now

    def function(self, name: str):
        def run() -> None:
            self.calls.append(name)
            timed = sum(c == name for c in self.calls) - self.warmup
            if timed > 0:
                self.now += self.durations[name][timed - 1]

        return run


DURATIONS = {"a": [1.0, 2.0, 3.0, 4.0, 5.0], "b": [10.0, 10.0, 10.0, 10.0, 50.0], "c": [5, 1, 4, 2, 3]}


def _time_fake(durations=DURATIONS, warmup=1):
    clock = FakeClock(durations)
    clock.warmup = warmup
    fns = {name: clock.function(name) for name in durations}
    rounds = time_rounds(fns, torch.device("cpu"), len(durations["a"]), warmup, clock=clock)
    return rounds, clock


def test_time_rounds_times_each_function_once_per_round_in_the_rotating_order():
    rounds, clock = _time_fake()
    names = list(DURATIONS)
    warm, timed = clock.calls[: 3 * 1], clock.calls[3:]
    assert sorted(warm) == names
    assert timed == [name for order in rounds.orders for name in order]
    assert rounds.orders == [[names[i] for i in round_order(3, r)] for r in range(5)]
    assert rounds.seconds == {k: [float(x) for x in v] for k, v in DURATIONS.items()}
    rows = rounds.csv_rows()
    assert len(rows) == 15 and Counter((row["round"], row["model"]) for row in rows) == Counter(
        {(r, name): 1 for r in range(5) for name in names}
    )
    assert [row["seconds"] for row in rows if row["model"] == "b"] == [10, 10, 10, 10, 50]


def test_spread_is_median_quartiles_and_range_over_rounds():
    s = Spread.of([5, 1, 4, 2, 3, 10, 7])  # sorted 1 2 3 4 5 7 10
    assert (s.median, s.q1, s.q3, s.low, s.high) == (4, 2.5, 6, 1, 10)


def test_a_ratio_is_taken_per_round_not_between_medians():
    spread, ratios = ratio_spread(DURATIONS["a"], DURATIONS["b"])
    assert ratios == pytest.approx([0.1, 0.2, 0.3, 0.4, 0.1])
    assert (spread.median, spread.low, spread.high) == pytest.approx((0.2, 0.1, 0.4))
    # the ratio of the medians would be 3 / 10


def test_a_row_gets_the_median_and_spread_of_its_own_times_over_the_rounds():
    rounds, _ = _time_fake()
    prepared = [(Row("b model", None, key="b"), print), (Row("c", None), print), (Row("x", None), None)]
    b, c, x = timed_rows(prepared, rounds)
    assert (b.seconds, b.spread.low, b.spread.high) == (10, 10, 50)
    assert (c.seconds, c.spread.q1, c.spread.q3) == (3, 2, 4)
    assert x.seconds is None and x.spread is None


def _rows(rounds: Rounds) -> dict[str, Row]:
    notes = {"kpcn": "x, diffuse+specular x 28 inputs", "kpcn_frame": "x, radiance x 62 inputs"}
    rows = {}
    for key, seconds in rounds.seconds.items():
        depth = {"unet_kpcn": 13, "kpcn": 9, "kpcn_frame": 9}.get(key)
        row = Row(key, statistics.median(seconds), note=notes.get(key, "pyoidn"), depth=depth, width="w")
        row.spread = Spread.of(seconds)
        rows[key] = row
    return rows


def test_the_claims_are_per_round_ratios_of_unet_kpcn_over_each_reference():
    rounds = Rounds(
        seconds={
            "unet_kpcn": [1.0, 1.0, 2.0, 1.0, 1.0],
            "kpcn": [20.0, 50.0, 10.0, 25.0, 20.0],  # ratios .05 .02 .2 .04 .05
            "kpcn_frame": [10.0, 10.0, 10.0, 10.0, 10.0],  # .1 .1 .2 .1 .1
            "oidn": [0.4, 0.5, 1.0, 0.6, 0.5],  # 2.5 2 2 1.667 2
        },
        orders=[[]] * 5,
    )
    lines = format_claims(_rows(rounds), rounds)
    kpcn = next(line for line in lines if "unet_kpcn / kpcn (" in line)
    assert "0.05x [0.02 - 0.2] = 20x faster" in kpcn and "met in 4/5 rounds" in kpcn
    assert "diffuse+specular x 28 inputs" in kpcn
    frame = next(line for line in lines if "unet_kpcn / kpcn_frame (" in line)
    assert "0.1x [0.1 - 0.2] = 10x faster" in frame and "met in 4/5 rounds" in frame
    assert "radiance x 62 inputs" in frame
    oidn = next(line for line in lines if "unet_kpcn / oidn (" in line)
    assert "2x [1.67 - 2.5]" in oidn and "met in 4/5 rounds" in oidn and "faster" not in oidn
    assert lines[-1].endswith("unet_kpcn 13 (w), kpcn 9 (w), kpcn_frame 9 (w)")
    spreads = format_spreads(list(_rows(rounds).values()), 5, 1)
    kpcn_spread = next(line for line in spreads.splitlines() if line.startswith("  kpcn "))
    assert kpcn_spread.split()[1:] == [
        "20.0000",
        "20.0000",
        "-",
        "25.0000",
        "10.0000",
        "-",
        "50.0000",
        "200%",
    ]
    ratios = format_ratios(_rows(rounds), rounds)
    assert ratios[1].startswith("  KPCN / DPCN time:  n/a")


def test_missing_reference_prints_na_and_no_unet_prints_no_claims():
    rounds = Rounds(seconds={"unet_kpcn": [1.0] * 5, "oidn": [1.0] * 5}, orders=[[]] * 5)
    lines = format_claims(_rows(rounds), rounds)
    assert "  unet_kpcn / kpcn: n/a (kpcn not timed)" in lines
    rows = _rows(rounds) | {"kpcn_frame": Row("kpcn_frame", None, note="unavailable (no GPU)")}
    assert "  unet_kpcn / kpcn_frame: n/a (kpcn_frame unavailable (no GPU))" in format_claims(rows, rounds)
    assert format_claims({"oidn": _rows(rounds)["oidn"]}, rounds) == []


def test_too_few_rounds_is_one_line_exit_2(capsys):
    assert bench_main([*TINY, "--rounds", "4"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "--rounds" in err and ">= 5" in err and "found 4" in err


def test_kpcn_frame_is_the_kpcn_the_volumetric_study_trains():
    """`kpcn_frame` gets the inputs and branch that `+sweep=unet_vs_kpcn model=kpcn` gives KPCN (the
    sweep's dataset=volumetric), not the still images' two branches of 28."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from src.bench.model_configs import CONF_DIR

    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        study = compose("config", overrides=["+sweep=unet_vs_kpcn", "model=kpcn", "profile=paper"])
    study_model = OmegaConf.to_container(study.model, resolve=True)
    frame = bench_config("kpcn_frame", "paper")
    assert frame == study_model
    assert (frame["in_channels"], frame["branches"]) == (62, ["radiance"])
    assert bench_config("kpcn", "paper")["in_channels"] == 28


def test_path_depth_follows_the_longest_chain_through_other_and_in_place_ops():
    conv = torch.nn.Conv2d(2, 2, 1)
    x = torch.rand(1, 2, 4, 4)

    def two_then_one():
        deep = torch.relu(conv(conv(x)))  # 2 convs
        side = torch.cat([conv(x), x], 1)[:, :2]  # 1 conv
        out = torch.zeros_like(x)  # 0
        out.add_(deep * 2)  # in place: now 2 deep
        return {"a": out + side, "b": side}

    assert path_depth(two_then_one) == 2
    assert path_depth(lambda: x + 1) == 0


def test_conv_depth_counts_layers_on_the_longest_path():
    kpcn = bench_config("kpcn_frame", "smoke")
    assert conv_depth(build_method(kpcn)) == kpcn["depth"]
    cfg = bench_config("unet_kpcn", "paper")
    scales, convs = len(cfg["widths"]), cfg["convs_per_level"]
    # down the encoder and up the decoder, the kernel head, then the finest scale compositor's 2 convs
    assert conv_depth(build_method(cfg)) == convs * (2 * scales - 1) + 1 + 2 == 13


def _read_csv(path: Path) -> tuple[list[str] | None, list[dict[str, str]]]:
    with path.open() as f:
        reader = csv.DictReader(f)
        return reader.fieldnames, list(reader)


def test_rounds_csv_has_one_row_per_model_per_round_in_the_order_they_ran(tmp_path):
    from src.bench.bench_log import write_rounds_csv

    rounds, _ = _time_fake()
    columns, rows = _read_csv(write_rounds_csv(tmp_path / "rounds.csv", rounds))
    assert columns == ["round", "model", "seconds"]
    assert [(int(r["round"]), r["model"]) for r in rows] == [
        (i, name) for i, order in enumerate(rounds.orders) for name in order
    ]
    assert [float(r["seconds"]) for r in rows if r["model"] == "c"] == [5, 1, 4, 2, 3]
    assert [p.name for p in tmp_path.iterdir()] == ["rounds.csv"]  # no temporary left


@pytest.mark.slow  # an MLflow SQLite store: ~40 schema migrations, 5-10 s on the shared 2-core machine
def test_log_writes_one_run_with_the_rounds_csv(tmp_path, monkeypatch, capsys):
    import mlflow
    from mlflow.tracking import MlflowClient

    monkeypatch.chdir(tmp_path)
    uri = f"sqlite:///{tmp_path}/bench.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    argv = [*TINY, "--rounds", "5", "--warmup", "0", "--models", "unet_kpcn,kpcn,kpcn_frame", "--log"]
    assert bench_main(argv) == 0
    out = capsys.readouterr().out
    assert "unet_kpcn / kpcn_frame (" in out and "logged: MLflow run" in out
    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name("nrbench-bench")
    (run,) = client.search_runs([experiment.experiment_id])
    assert run.info.status == "FINISHED"
    params, tags, metrics = run.data.params, run.data.tags, run.data.metrics
    assert params["bench"] == "denoise" and params["rounds"] == "5" and params["warmup"] == "0"
    assert (params["width"], params["height"], params["device"], params["tile"]) == ("16", "12", "cpu", "256")
    assert tags["nrbench.profile"] == "paper" and tags["nrbench.device"] == "cpu"
    assert len(tags["nrbench.git_commit"]) in (40, len("unknown"))
    local = Path(
        mlflow.artifacts.download_artifacts(
            run_id=run.info.run_id, artifact_path="bench/rounds.csv", tracking_uri=uri
        )
    )
    columns, rows = _read_csv(local)
    assert columns == ["round", "model", "seconds"]
    models = {"unet_kpcn", "kpcn", "kpcn_net_only", "kpcn_frame", "kpcn_frame_net_only", "oidn", "conv2d"}
    assert {r["model"] for r in rows} == models
    assert Counter((r["round"], r["model"]) for r in rows) == Counter(
        {(str(i), m): 1 for i in range(5) for m in models}
    )
    assert len({next(r["model"] for r in rows if r["round"] == str(i)) for i in range(5)}) == 5  # rotates
    for model in models:
        seconds = [float(r["seconds"]) for r in rows if r["model"] == model]
        assert metrics[f"seconds_{model}"] == pytest.approx(statistics.median(seconds))


def test_the_bench_prints_spreads_and_the_claims_against_both_kpcn_forms_and_oidn(capsys):
    argv = ["denoise", "--profile", "smoke", "--width", "16", "--height", "12", "--device", "cpu"]
    assert bench_main([*argv, "--rounds", "5", "--warmup", "0", "--models", "unet_kpcn,kpcn,kpcn_frame"]) == 0
    out = capsys.readouterr().out
    assert "median of 5 rounds after 0 warm-up" in out
    for key in ("kpcn", "kpcn_frame", "oidn"):
        assert sum(line.startswith(f"  unet_kpcn / {key} (") for line in out.splitlines()) == 1
    spreads = out.split("seconds per frame over 5 rounds")[1].split("ratios")[0]
    assert [line.split()[0] for line in spreads.splitlines()[2:]] == [
        "unet_kpcn", "kpcn", "kpcn", "kpcn_frame", "kpcn_frame", "oidn", "conv2d"
    ]  # fmt: skip
    assert "conv layers on the longest input-to-output path (hidden channels): unet_kpcn " in out


def test_log_to_an_unusable_store_is_one_line_exit_2_after_the_report(tmp_path, monkeypatch, capsys):
    (tmp_path / "file").write_text("")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path}/file/mlflow.db")  # under a file
    argv = ["denoise", "--profile", "smoke", "--width", "16", "--height", "12", "--device", "cpu"]
    assert bench_main([*argv, "--rounds", "5", "--models", "unet_kpcn", "--no-oidn", "--log"]) == 2
    captured = capsys.readouterr()
    assert "seconds per frame over 5 rounds" in captured.out  # the measurement is not lost
    err = captured.err.strip()
    assert "\n" not in err and "tracking.uri=" in err and "mlflow.db" in err
