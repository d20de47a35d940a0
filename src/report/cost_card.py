"""The cost card's reference: the device's measured peak, which a run's achieved GFLOP/s is a fraction of.

The one peak is the bench's (`python -m src.bench denoise`, whose reference row is a plain 100 -> 100 5x5
`conv2d` over the same frame, src/bench/peak.py): a bench run in the report's tracking store (experiment
`nrbench-bench`, metric `seconds_conv2d`, params `width` and `height`, tag `nrbench.device_name`) gives
its device's peak as 2 x 100 x 100 x 25 FLOPs per pixel x pixels / seconds; the highest of a device's bench
runs is its peak. A run whose device has no bench run has no fraction (the cost table leaves it blank).
"""

from __future__ import annotations

import logging

import mlflow
import pandas as pd

log = logging.getLogger("nrbench.report")

BENCH_EXPERIMENT = "nrbench-bench"
DEVICE_TAG = "tags.nrbench.device_name"
#: The bench's reference convolution (src/bench/peak.py `BASELINE_CONV`): FLOPs per output pixel.
CONV_FLOPS_PER_PIXEL = 2.0 * 100 * 100 * 5 * 5


def measured_peaks(bench_runs: pd.DataFrame) -> dict[str, float]:
    """GFLOP/s per device name: the best reference convolution of the bench runs (`mlflow.search_runs`
    rows) on that device."""
    needed = ("metrics.seconds_conv2d", "params.width", "params.height", DEVICE_TAG)
    if bench_runs.empty or any(c not in bench_runs for c in needed):
        return {}
    rows = bench_runs.dropna(subset=list(needed))
    pixels = pd.to_numeric(rows["params.width"]) * pd.to_numeric(rows["params.height"])
    gflops = CONV_FLOPS_PER_PIXEL * pixels / pd.to_numeric(rows["metrics.seconds_conv2d"]) / 1e9
    return {str(k): float(v) for k, v in gflops.groupby(rows[DEVICE_TAG]).max().items()}


def with_peak_fraction(runs: pd.DataFrame, peaks: dict[str, float] | None = None) -> pd.DataFrame:
    """`runs` with `metrics.eval_peak_fraction` (achieved eval GFLOP/s over its device's measured peak)
    where both are known; `peaks` by device name, read from the store's bench runs when None."""
    if "metrics.eval_gflops" not in runs or DEVICE_TAG not in runs:
        return runs
    if peaks is None:
        peaks = _store_peaks()
    peak = runs[DEVICE_TAG].map(peaks)
    return runs.assign(**{"metrics.eval_peak_fraction": pd.to_numeric(runs["metrics.eval_gflops"]) / peak})


def _store_peaks() -> dict[str, float]:
    """`measured_peaks` of the bench runs in the current tracking store (none when it has none)."""
    try:
        if mlflow.get_experiment_by_name(BENCH_EXPERIMENT) is None:
            return {}
        return measured_peaks(mlflow.search_runs(experiment_names=[BENCH_EXPERIMENT], output_format="pandas"))
    except Exception as err:  # an unreachable store: the cost table simply has no fraction, logged
        log.info("report: no bench runs read (%s); no fraction of peak", err)
        return {}
