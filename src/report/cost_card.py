"""The cost card's reference: the device's measured peak, which a run's achieved GFLOP/s is a fraction of.

The one peak is the bench's (`python -m src.bench denoise`, whose reference row is a plain 100 -> 100 5x5
`conv2d` over the same frame, src/bench/peak.py): a bench run in the report's tracking store (experiment
`nrbench-bench`, metric `seconds_conv2d`, params `width` and `height`, tags `nrbench.device_name` and
`nrbench.precision`) gives that device's peak at that precision as 2 x 100 x 100 x 25 FLOPs per pixel x
pixels / seconds; the highest of such bench runs is the peak. A run is compared with the peak of its own
device and precision (a bf16 bench is no peak for an fp32 evaluation); without one (no such bench run, or
bench runs from before they were tagged with their precision) it has no fraction and the cost table leaves
the cell blank.
"""

from __future__ import annotations

import logging

import mlflow
import pandas as pd

log = logging.getLogger("nrbench.report")

BENCH_EXPERIMENT = "nrbench-bench"
DEVICE_TAG = "tags.nrbench.device_name"
PRECISION_TAG = "tags.nrbench.precision"
#: The bench's reference convolution (src/bench/peak.py `BASELINE_CONV`): FLOPs per output pixel.
CONV_FLOPS_PER_PIXEL = 2.0 * 100 * 100 * 5 * 5


def measured_peaks(bench_runs: pd.DataFrame) -> dict[tuple[str, str], float]:
    """GFLOP/s per (device name, precision): the best reference convolution of the bench runs
    (`mlflow.search_runs` rows) on that device at that precision."""
    needed = ("metrics.seconds_conv2d", "params.width", "params.height", DEVICE_TAG, PRECISION_TAG)
    if bench_runs.empty or any(c not in bench_runs for c in needed):
        return {}
    rows = bench_runs.dropna(subset=list(needed))
    pixels = pd.to_numeric(rows["params.width"]) * pd.to_numeric(rows["params.height"])
    gflops = CONV_FLOPS_PER_PIXEL * pixels / pd.to_numeric(rows["metrics.seconds_conv2d"]) / 1e9
    best = gflops.groupby([rows[DEVICE_TAG], rows[PRECISION_TAG]]).max()
    return {(str(d), str(p)): float(v) for (d, p), v in best.items()}


def with_peak_fraction(runs: pd.DataFrame, peaks: dict[tuple[str, str], float] | None = None) -> pd.DataFrame:
    """`runs` with `metrics.eval_peak_fraction` (achieved eval GFLOP/s over the measured peak of its
    device and precision) where both are known; `peaks` as `measured_peaks` gives them, read from the
    store's bench runs when None."""
    if any(c not in runs for c in ("metrics.eval_gflops", DEVICE_TAG, PRECISION_TAG)):
        return runs
    if peaks is None:
        peaks = _store_peaks()
    keys = zip(runs[DEVICE_TAG].astype(str), runs[PRECISION_TAG].astype(str), strict=True)
    peak = pd.Series([peaks.get(k, float("nan")) for k in keys], index=runs.index)
    return runs.assign(**{"metrics.eval_peak_fraction": pd.to_numeric(runs["metrics.eval_gflops"]) / peak})


def _store_peaks() -> dict[tuple[str, str], float]:
    """`measured_peaks` of the bench runs in the current tracking store (none when it has none)."""
    try:
        if mlflow.get_experiment_by_name(BENCH_EXPERIMENT) is None:
            return {}
        return measured_peaks(mlflow.search_runs(experiment_names=[BENCH_EXPERIMENT], output_format="pandas"))
    except Exception as err:  # an unreachable store: the cost table simply has no fraction, logged
        log.info("report: no bench runs read (%s); no fraction of peak", err)
        return {}
