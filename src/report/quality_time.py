"""Quality against time: each training run's held-out (validation) metric against its training clock, per
compared arm with the seeds' spread, and the two numbers a reader asks of it.

Every validation point of a training logs the metric and `train_time_s` at the same step (the clock covers
the training batches and optimiser steps, not validation or logging: src/train/loop.py); every generation
of a filter search logs its fitness and `search_time_s` (the search's seconds over every job that ran it).
The metric is the first of `METRICS` every run logged: NeRF's validation PSNR (higher is better), a
denoiser's validation loss (`val_loss_total`, else `val_loss_color`; lower is better), or the search's
minimum fitness so far (`search_best_so_far`, lower is better).

- `quality_vs_time.png`: per arm (the runs sharing the report's axis values), the median over seeds of the
  metric interpolated on a common clock, and the band from the seeds' minimum to maximum, where every seed
  has reached that time;
- `quality_vs_time.{md,tex,csv}`: per arm, mean ± std over seeds of the final value, the training seconds,
  the seconds to reach X and the value at T seconds. X is the worst arm's mean final value (what every arm
  is asked to reach), T the shortest arm's mean training time (the longest time every arm trained). A seed
  that never reaches X has no time (`reached` gives the share that did): a failure shown, never dropped.

Runs logged before the training clock was recorded at each validation point have one point (the final
step) and are left out of both, logged.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only, also on a machine without a display

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402

from src.report.collect import DEFAULT_AXES  # noqa: E402
from src.report.figures import row_colors, save_figure  # noqa: E402
from src.report.tables import MetricSpec, aggregate, axis_keys  # noqa: E402

log = logging.getLogger("nrbench.report")

STEM = "quality_vs_time"
HEADING = "Quality against training time"
#: (metric, higher is better, axis label, its clock), the first that every run logged is drawn.
METRICS = (
    ("val_psnr", True, "validation PSNR (dB)", "train_time_s"),
    ("val_loss_total", False, "validation loss (total)", "train_time_s"),
    ("val_loss_color", False, "validation loss (colour)", "train_time_s"),
    ("search_best_so_far", False, "search fitness (min so far)", "search_time_s"),
)


def time_to_reach(seconds: np.ndarray, values: np.ndarray, target: float, higher: bool) -> float:
    """The first time a curve reaches `target`, linear between its points (NaN if it never does): the
    curve's points (seconds increasing) are checked in order; between the last point short of the target
    and the first one at or past it, the crossing is interpolated."""
    reached = values >= target if higher else values <= target
    if not reached.any():
        return float("nan")
    i = int(np.argmax(reached))
    if i == 0:
        return float(seconds[0])
    t0, t1, v0, v1 = seconds[i - 1], seconds[i], values[i - 1], values[i]
    return float(t0 + (target - v0) * (t1 - t0) / (v1 - v0))


def value_at(seconds: np.ndarray, values: np.ndarray, time: float) -> float:
    """The curve's value at `time`, linear between its points; NaN past its last point (it did not train
    that long) or before its first."""
    if time > seconds[-1] or time < seconds[0]:
        return float("nan")
    return float(np.interp(time, seconds, values))


def curve(client: MlflowClient, run_id: str, metric: str, clock_key: str) -> tuple[np.ndarray, np.ndarray]:
    """(seconds, values) of `metric` at the steps where the run also logged the clock `clock_key`, in step
    order."""
    clock = {m.step: m.value for m in client.get_metric_history(run_id, clock_key)}
    points = sorted((m.step, m.value) for m in client.get_metric_history(run_id, metric) if m.step in clock)
    steps = dict(points)  # one value per step (a repeated step keeps its last)
    seconds = np.array([clock[s] for s in steps], dtype=np.float64)
    return seconds, np.array(list(steps.values()), dtype=np.float64)


def _arms(runs: pd.DataFrame, axes: Sequence[str]) -> pd.Series:
    """Each run's arm: its axis values joined by " / "."""
    return axis_keys(runs, axes).agg(" / ".join, axis=1)


def quality_against_time(
    runs: pd.DataFrame, out_png: Path, axes: Sequence[str] | None = None
) -> tuple[Path | None, pd.DataFrame | None]:
    """The figure and the table of the module docstring; (None, None) when no run has a curve of the first
    metric (and its clock) that every run logged."""
    axes = list(axes or DEFAULT_AXES)
    logged = [
        m
        for m in METRICS
        if all(f"metrics.{k}" in runs and runs[f"metrics.{k}"].notna().all() for k in (m[0], m[3]))
    ]
    if not logged:
        return None, None
    metric, higher, label, clock_key = logged[0]
    client = MlflowClient()
    curves, arm_of = {}, {}
    for (_, run), arm in zip(runs.iterrows(), _arms(runs, axes), strict=True):
        seconds, values = curve(client, run["run_id"], metric, clock_key)
        if len(seconds) < 2:
            log.info(
                "report: run %s has no %s beside its %s; not in %s", run["run_id"], clock_key, metric, STEM
            )
            continue
        curves[run["run_id"]], arm_of[run["run_id"]] = (seconds, values), arm
    if not curves:
        return None, None
    figure = _figure(curves, arm_of, label, clock_key, out_png)
    return figure, time_table(runs, curves, higher, axes, label, clock_key)


def time_table(
    runs: pd.DataFrame,
    curves: dict,
    higher: bool,
    axes: list[str],
    label: str,
    clock_key: str = "train_time_s",
) -> pd.DataFrame:
    finals = pd.DataFrame(
        {
            "final": {r: v[-1] for r, (_, v) in curves.items()},
            "seconds": {r: s[-1] for r, (s, _) in curves.items()},
        }
    )
    arms = _arms(runs.set_index("run_id").loc[list(curves)].reset_index(), axes).set_axis(list(curves))
    by_arm = finals.groupby(arms).mean()
    target = float(by_arm["final"].min() if higher else by_arm["final"].max())
    horizon = float(by_arm["seconds"].min())
    rows = runs[runs["run_id"].isin(curves)].copy()
    values = {}
    for run_id, (seconds, ys) in curves.items():
        reach = time_to_reach(seconds, ys, target, higher)
        values[run_id] = {
            "metrics.qt_final": ys[-1],
            "metrics.qt_seconds": seconds[-1],
            "metrics.qt_time_to": reach,
            "metrics.qt_reached": float(not np.isnan(reach)),
            "metrics.qt_at": value_at(seconds, ys, horizon),
        }
    rows = rows.join(pd.DataFrame.from_dict(values, orient="index"), on="run_id")
    fmt = "{:.2f}" if higher else "{:.4g}"
    specs: dict[str, MetricSpec] = {
        f"final {label}": ("qt_final", higher, fmt),
        "train s": ("qt_seconds", False, "{:.1f}"),
        f"s to reach {fmt.format(target)}": ("qt_time_to", False, "{:.1f}"),
        "reached": ("qt_reached", None, "{:.0%}"),
        f"at {horizon:.1f} s": ("qt_at", higher, fmt),
    }
    table = aggregate(rows, axes, specs)
    table.attrs["notes"] = [
        f"{label} against the clock {clock_key} (training: batches and optimiser steps, not validation; a "
        "search: its generations); "
        f"X = {fmt.format(target)}, the worst arm's mean final value; T = {horizon:.1f} s, the shortest "
        "arm's mean training time; a seed that never reaches X has no time ('reached' is the share that did)"
    ]
    return table


def arm_bands(
    curves: dict, arm_of: dict
) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, int]]:
    """Per arm (in the order its first run appears): (clock, median, minimum, maximum, seeds) of its
    runs' curves on the union of their clock points up to the earliest last point (where every seed has a
    value), each curve linear between its own points."""
    bands = {}
    for arm in dict.fromkeys(arm_of.values()):
        members = [curves[r] for r, a in arm_of.items() if a == arm]
        grid = np.unique(np.concatenate([s for s, _ in members]))
        grid = grid[grid <= min(s[-1] for s, _ in members)]
        stack = np.array([np.interp(grid, s, v) for s, v in members])
        bands[arm] = (grid, np.median(stack, axis=0), stack.min(axis=0), stack.max(axis=0), len(members))
    return bands


def _figure(curves: dict, arm_of: dict, label: str, clock_key: str, out_png: Path) -> Path:
    fig, ax = plt.subplots(figsize=(6.5, 4.2), layout="constrained")
    bands = arm_bands(curves, arm_of)
    colors = row_colors(list(bands))  # an arm's colour in the report's other plots
    for arm, (grid, median, low, high, seeds) in bands.items():
        color = colors[arm]
        ax.plot(grid, median, color=color, label=f"{arm} ({seeds} seeds)")
        if seeds > 1:
            ax.fill_between(grid, low, high, color=color, alpha=0.2, linewidth=0)
    ax.set_xlabel(f"seconds ({clock_key})")
    ax.set_ylabel(label)
    ax.set_title("median over seeds; band: their min to max", fontsize="small")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize="small", frameon=False)
    return save_figure(fig, out_png)
