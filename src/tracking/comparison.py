"""Comparison of logged runs: one row per run of a sweep or an experiment, as a frame and as plain text."""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import mlflow
import pandas as pd
from mlflow.utils.mlflow_tags import MLFLOW_PARENT_RUN_ID

# Default comparison columns: display name -> column of `mlflow.search_runs`' frame.
DEFAULT_COLUMNS: dict[str, str] = {
    "model": "tags.nrbench.model",
    "params": "metrics.param_count",
    "PSNR": "metrics.eval_psnr",
    "SSIM": "metrics.eval_ssim",
    "relMSE (Bako)": "metrics.eval_relmse",
    "noisy relMSE (Bako)": "metrics.eval_noisy_relmse",
    "relMSE / noisy": "metrics.eval_relmse_ratio",
    "train time s": "metrics.train_time_s",
    "inference ms/MP": "metrics.eval_ms_per_mpixel",
    "status": "status",
}
_SORT_COLUMN = "relMSE (Bako)"
# Per-column display formats for `format_table`; other float columns use `{:.4g}`.
_FORMATS: dict[str, str] = {
    "params": "{:,.0f}",
    "PSNR": "{:.2f}",
    "SSIM": "{:.4f}",
    "relMSE (Bako)": "{:.4g}",
    "noisy relMSE (Bako)": "{:.4g}",
    "relMSE / noisy": "{:.4g}",
    "train time s": "{:.1f}",
    "inference ms/MP": "{:.1f}",
}


def comparison_table(
    parent_run_id: str | None = None,
    experiment: str | None = None,
    columns: Mapping[str, str] | None = None,
) -> pd.DataFrame:
    """One row per run: the children of `parent_run_id`, or else every job run of `experiment`.

    `columns` maps display names to `mlflow.search_runs` columns (`metrics.x`, `params.x`, `tags.x`,
    `status`, ...); one a run lacks shows NaN. Rows are sorted by relMSE, best first, when shown.
    """
    columns = dict(DEFAULT_COLUMNS if columns is None else columns)
    runs = _search(parent_run_id, experiment)
    missing = pd.Series(math.nan, index=runs.index)
    table = pd.DataFrame({name: runs.get(col, missing) for name, col in columns.items()})
    if _SORT_COLUMN in table:
        table = table.sort_values(_SORT_COLUMN, na_position="last", kind="stable")
    return table.reset_index(drop=True)


def _search(parent_run_id: str | None, experiment: str | None) -> pd.DataFrame:
    """`mlflow.search_runs` frame for the chosen runs (sweep parents excluded)."""
    if parent_run_id is None and experiment is None:
        raise ValueError("comparison_table needs a parent_run_id or an experiment")
    where = f"tags.{MLFLOW_PARENT_RUN_ID} = '{parent_run_id}'" if parent_run_id else ""
    scope = {"experiment_names": [experiment]} if experiment else {"search_all_experiments": True}
    runs = mlflow.search_runs(filter_string=where, output_format="pandas", **scope)
    if "tags.nrbench.sweep_parent" in runs:
        runs = runs[runs["tags.nrbench.sweep_parent"] != "true"]
    # Oldest first, so equal relMSE (or none) keeps the sweep's job order.
    return runs.sort_values("start_time", kind="stable") if "start_time" in runs else runs


def _formatter(column: str, values: pd.Series):
    """Formatter for one column: its `_FORMATS` entry, `{:.4g}` for other floats, `-` for missing."""
    fmt = _FORMATS.get(column)
    if fmt is None and pd.api.types.is_float_dtype(values):
        fmt = "{:.4g}"

    def render(value: Any) -> str:
        if value is None or (isinstance(value, float) and math.isnan(value)):
            return "-"
        if fmt is not None and isinstance(value, int | float):
            return fmt.format(value)
        return str(value)

    return render


def format_table(df: pd.DataFrame) -> str:
    """Plain-text table (no `tabulate` needed) with per-column number formats and `-` for missing."""
    if df.empty:
        return "(no runs)"
    formatters = {col: _formatter(col, df[col]) for col in df.columns}
    return df.to_string(index=False, formatters=formatters, na_rep="-")
