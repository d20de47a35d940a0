"""Quality against time (src/report/quality_time.py): the crossing time and the value at a time of a
curve, by closed form on both sides of each rule."""

from __future__ import annotations

import math

import numpy as np
import pytest

from src.report.quality_time import time_to_reach, value_at

SECONDS = np.array([0.0, 10.0, 20.0, 40.0])
LOSS = np.array([1.0, 0.5, 0.3, 0.2])  # lower is better
PSNR = np.array([20.0, 25.0, 27.0, 28.0])  # higher is better


def test_the_crossing_is_interpolated_between_the_two_points_around_it():
    assert time_to_reach(SECONDS, LOSS, 0.4, higher=False) == pytest.approx(15.0)  # 0.5 -> 0.3 over 10-20 s
    assert time_to_reach(SECONDS, PSNR, 27.5, higher=True) == pytest.approx(30.0)
    assert time_to_reach(SECONDS, LOSS, 0.5, higher=False) == pytest.approx(10.0)  # reached on a point


def test_a_target_never_reached_has_no_time_and_one_reached_at_once_the_first():
    assert math.isnan(time_to_reach(SECONDS, LOSS, 0.1, higher=False))
    assert math.isnan(time_to_reach(SECONDS, PSNR, 29.0, higher=True))
    assert time_to_reach(SECONDS + 5, LOSS, 2.0, higher=False) == 5.0
    # the direction matters: 0.4 is "reached" at once when higher is better
    assert time_to_reach(SECONDS, LOSS, 0.4, higher=True) == 0.0


def test_the_value_at_a_time_is_linear_inside_the_curve_and_undefined_past_it():
    assert value_at(SECONDS, LOSS, 30.0) == pytest.approx(0.25)
    assert value_at(SECONDS, LOSS, 40.0) == pytest.approx(0.2)
    assert math.isnan(value_at(SECONDS, LOSS, 40.1))
    assert math.isnan(value_at(SECONDS + 1, LOSS, 0.5))


def test_the_table_asks_every_arm_for_the_worst_final_value_and_the_shortest_time():
    import pandas as pd

    from src.report.quality_time import time_table

    runs = pd.DataFrame(
        {"run_id": ["a0", "a1", "b0", "b1"], "params.model.name": ["fast", "fast", "slow", "slow"]}
    )
    curves = {  # lower is better; "fast" ends at 0.2 after 40 s, "slow" at 0.4 (0.3, 0.5) after 100 s
        "a0": (np.array([0.0, 20.0, 40.0]), np.array([1.0, 0.4, 0.2])),
        "a1": (np.array([0.0, 20.0, 40.0]), np.array([1.0, 0.6, 0.2])),
        "b0": (np.array([0.0, 50.0, 100.0]), np.array([1.0, 0.5, 0.3])),
        "b1": (np.array([0.0, 50.0, 100.0]), np.array([1.0, 0.7, 0.5])),
    }
    table = time_table(runs, curves, False, ["model.name"], "loss")
    target_column = next(c for c in table.columns if c.startswith("s to reach") and not c.endswith("std"))
    at_column = next(c for c in table.columns if c.startswith("at ") and not c.endswith("std"))
    assert (
        target_column == "s to reach 0.4" and at_column == "at 40.0 s"
    )  # X: slow's mean 0.4; T: fast's 40 s
    fast, slow = table.loc["fast"], table.loc["slow"]
    # a0 reaches 0.4 at 20 s, a1 between 20 s (0.6) and 40 s (0.2) at 30 s; b0 at 75 s; b1 never
    assert fast[target_column] == pytest.approx(25.0) and fast["reached"] == 1.0
    assert slow[target_column] == pytest.approx(75.0) and slow["reached"] == 0.5
    assert fast[at_column] == pytest.approx(0.2)
    assert slow[at_column] == pytest.approx(np.mean([1.0 - 0.5 * 40 / 50, 1.0 - 0.3 * 40 / 50]))
    assert fast["train s"] == 40.0 and slow["runs"] == 2


def test_each_arms_band_is_its_seeds_median_min_and_max_where_every_seed_has_a_value():
    from src.report.quality_time import arm_bands

    curves = {
        "b0": (np.array([0.0, 30.0]), np.array([2.0, 1.0])),  # one seed: its own curve
        "a0": (np.array([0.0, 20.0, 40.0]), np.array([1.0, 0.4, 0.2])),
        "a1": (np.array([0.0, 10.0, 40.0, 50.0]), np.array([0.8, 0.5, 0.35, 0.1])),
        "a2": (np.array([0.0, 40.0, 45.0]), np.array([0.9, 0.3, 0.3])),
    }
    arm_of = {"b0": "slow", "a0": "fast", "a1": "fast", "a2": "fast"}
    bands = arm_bands(curves, arm_of)
    assert list(bands) == ["slow", "fast"]  # the order runs first appear in
    grid, median, low, high, seeds = bands["fast"]
    assert seeds == 3 and grid.tolist() == [0.0, 10.0, 20.0, 40.0]  # a0 ends at 40 s: nothing past it
    # each seed at 0, 10, 20, 40 s, linear between its own points
    a0 = [1.0, 0.7, 0.4, 0.2]
    a1 = [0.8, 0.5, 0.5 - 0.15 * 10 / 30, 0.35]
    a2 = [0.9, 0.9 - 0.6 * 10 / 40, 0.9 - 0.6 * 20 / 40, 0.3]
    stack = np.array([a0, a1, a2])
    np.testing.assert_allclose(median, np.median(stack, axis=0))
    np.testing.assert_allclose(low, stack.min(axis=0))
    np.testing.assert_allclose(high, stack.max(axis=0))
    grid, median, low, high, seeds = bands["slow"]
    assert seeds == 1 and grid.tolist() == [0.0, 30.0]
    assert median.tolist() == low.tolist() == high.tolist() == [2.0, 1.0]


def test_the_figure_draws_each_arms_median_and_band_from_the_logged_curves_in_its_report_colour(
    tmp_path, monkeypatch
):
    """Runs logged to a real MLflow store: each arm's line is its seeds' median on the common clock, its
    band spans their min and max, and its colour is the one `row_colors` gives that arm in the report's
    other plots; the table comes with it."""
    import mlflow
    import pandas as pd
    from matplotlib.collections import PolyCollection

    from src.report import quality_time
    from src.report.figures import row_colors

    uri = f"sqlite:///{tmp_path}/m.db"
    client = mlflow.MlflowClient(uri)
    experiment = client.create_experiment("qt", (tmp_path / "art").as_uri())
    logged = {  # arm -> per seed (seconds, PSNR) at steps 0, 1, 2
        "kpcn": [([0.0, 10.0, 20.0], [20.0, 24.0, 26.0]), ([0.0, 10.0, 20.0], [21.0, 25.0, 28.0])],
        "dpcn": [([0.0, 5.0, 30.0], [19.0, 22.0, 25.0]), ([0.0, 10.0, 30.0], [18.0, 20.0, 27.0])],
    }
    rows = []
    for arm, seeds in logged.items():
        for seconds, psnr in seeds:
            run = client.create_run(experiment).info.run_id
            for step, (s, v) in enumerate(zip(seconds, psnr, strict=True)):
                client.log_metric(run, "train_time_s", s, step=step)
                client.log_metric(run, "val_psnr", v, step=step)
            rows.append({"run_id": run, "params.model.name": arm, "metrics.val_psnr": psnr[-1],
                         "metrics.train_time_s": seconds[-1]})  # fmt: skip
    drawn = {}

    def keep(fig, path):
        drawn["fig"] = fig
        return path

    monkeypatch.setattr(quality_time, "save_figure", keep)
    # this store, whatever tracking URI an earlier test set in the process
    monkeypatch.setattr(quality_time, "MlflowClient", lambda: mlflow.MlflowClient(uri))
    figure, table = quality_time.quality_against_time(pd.DataFrame(rows), tmp_path / "qt.png")
    assert figure == tmp_path / "qt.png" and list(table.index) == ["kpcn", "dpcn"]
    ax = drawn["fig"].axes[0]
    lines = {line.get_label().split(" (")[0]: line for line in ax.get_lines()}
    colors = row_colors(["kpcn", "dpcn"])
    assert lines["kpcn"].get_color() == colors["kpcn"] and lines["dpcn"].get_color() == colors["dpcn"]
    assert lines["kpcn"].get_xdata().tolist() == [0.0, 10.0, 20.0]
    assert lines["kpcn"].get_ydata().tolist() == [20.5, 24.5, 27.0]
    # dpcn on 0, 5, 10, 30 s: seed 0 at 10 s is 22 + 3 * 5 / 25, seed 1 at 5 s is 19
    assert lines["dpcn"].get_xdata().tolist() == [0.0, 5.0, 10.0, 30.0]
    np.testing.assert_allclose(lines["dpcn"].get_ydata(), [18.5, 20.5, (22.6 + 20.0) / 2, 26.0])
    bands = [c for c in ax.collections if isinstance(c, PolyCollection)]
    assert len(bands) == 2
    kpcn_band = bands[0].get_paths()[0].vertices
    assert kpcn_band[:, 1].min() == 20.0 and kpcn_band[:, 1].max() == 28.0
