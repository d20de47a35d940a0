"""The `report` stage: tables, figures and an HTML page from the logged MLflow runs that `cfg.report`
selects, written to `<report.out_dir>/<report.name>/`:

    comparison.{md,tex,csv}           quality metrics per compared row (mean ± std over seeds)
    comparison_<value>.{md,tex,csv}   the same for one value of `report.tables_by` (e.g. one scene)
    comparison_per_spp.{md,tex,csv}   the same per noisy spp level (when the runs logged them)
    cost.{md,tex,csv}                 parameters, training time, iterations, inference time
    losses.{md,tex,csv}               final validation and training loss per component (learned models)
    per_image.{md,tex,csv}            relMSE, relMSE / noisy, energy, PSNR per row and held-out image
                                      (the runs' eval/per_image.csv; denoising and filter evaluations)
    paired.{md,tex,csv}               each row against the best row per metric, paired by seed and
                                      held-out image: ratio or difference, Wilcoxon p, shown / not shown
    feature_usage.{md,tex,csv}        task=filter_search: feature terminals of the runs' best expressions
    learning_curves.png, image_grid.png, index.html (self-contained)
    search_curves.png                 task=filter_search: best fitness per generation, one curve per run

Every file is written atomically. When no run matches, `DataError` names the filter that matched
nothing and no file is written.
"""

from __future__ import annotations

import logging
import re
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import mlflow

from src.io.atomic import atomic_write_text
from src.multirun import quiet_mlflow_logs
from src.report.collect import (
    DEFAULT_AXES,
    config_value,
    differing_params,
    find_runs,
    param_column,
    per_image_rows,
)
from src.report.figures import DEFAULT_CROP, image_grid, learning_curves, run_labels, search_curves
from src.report.html import render_html
from src.report.tables import (
    axis_label,
    comparison_table,
    config_values,
    cost_table,
    feature_usage_table,
    loss_table,
    paired_table,
    per_image_table,
    per_value_table,
    select_metrics,
    to_csv,
    to_latex,
    to_markdown,
)

log = logging.getLogger("nrbench.report")

#: The HTML page's heading of each table (by file stem) and of the image grid.
TABLE_HEADINGS = {
    "comparison": "Quality",
    "comparison_per_spp": "Quality per spp",
    "cost": "Cost",
    "losses": "Final losses (validation, then training)",
    "per_image": "Quality per held-out image",
    "paired": "Each row against the best, paired by seed and held-out image (Wilcoxon signed-rank)",
    "feature_usage": "Features of the best expressions (occurrences)",
}
SEARCH_HEADING = "Filter search: best fitness per generation"
_STEM_UNSAFE = re.compile(r"[^\w.-]")  # characters a per-value table's file name replaces by "_"
GRID_HEADING = "Test images (noisy | denoised | reference)"


#: Defaults of optional `report:` keys for a config that lacks them (a hand-built one, e.g. in the tests);
#: conf/config.yaml sets every key (`name` is the task's name there).
DEFAULT_REPORT_NAME = "report"
DEFAULT_OUT_DIR = "reports"
DEFAULT_IMAGES = 3


def _crop(cfg: Any) -> tuple[int, int]:
    """Crop size and zoom of the grid: `task.eval.crop_size` / `crop_zoom` when the config has both, else
    `DEFAULT_CROP` (logged). A value that is not an integer is an error, not a silent default."""
    e = config_value(config_value(cfg, "task"), "eval")
    size, zoom = config_value(e, "crop_size"), config_value(e, "crop_zoom")
    if size is None or zoom is None:
        log.info("report: no task.eval.crop_size/crop_zoom; the image grid crops %d px at x%d", *DEFAULT_CROP)
        return DEFAULT_CROP
    return int(size), int(zoom)


def _first_value_only(runs, columns_by: str | None):
    """The runs of the first value of `columns_by` (e.g. one scene): an image grid compares one image
    across models, so all its panels must come from the same scene."""
    column = param_column(str(columns_by)) if columns_by else None
    if column is None or column not in runs:
        return runs
    return runs[runs[column] == runs[column].iloc[0]]


def build_report(cfg: Any) -> dict[str, Any]:
    """Build the report for `cfg.report` (runs from `cfg.tracking.uri`); returns a summary: number of
    runs, output directory, written files and warnings."""
    rc = cfg.report
    tracking = config_value(cfg, "tracking")
    quiet_mlflow_logs()
    if tracking is not None and config_value(tracking, "uri"):
        mlflow.set_tracking_uri(str(tracking.uri))
    runs = find_runs(rc)  # raises DataError before anything is written

    axes = [str(a) for a in (config_value(rc, "axes") or DEFAULT_AXES)]
    columns_by, tables_by = config_value(rc, "columns_by"), config_value(rc, "tables_by")
    # What tells the runs apart besides the seed: the compared axes, and the column or table key (the scene).
    row_keys = [*axes, *(str(k) for k in dict.fromkeys((columns_by, tables_by)) if k)]
    warnings = _confounding_warnings(runs, axes, row_keys)
    metrics = select_metrics(config_value(rc, "metrics"))
    tables = _tables(runs, axes, row_keys, columns_by, metrics)
    tables |= _tables_by_value(runs, axes, tables_by, metrics)
    images = per_image_rows(runs)
    if (per_image := per_image_table(images, axes)) is not None:
        tables["per_image"] = per_image
    if (paired := paired_table(images, axes)) is not None:
        tables["paired"] = paired

    name = str(config_value(rc, "name", DEFAULT_REPORT_NAME))
    out_dir = Path(str(config_value(rc, "out_dir", DEFAULT_OUT_DIR))).expanduser() / name
    files = _write_tables(tables, out_dir, warnings)
    if (usage := feature_usage_table(runs)) is not None:  # no confounding notes: it compares no rows
        tables["feature_usage"] = usage
        files |= _write_tables({"feature_usage": usage}, out_dir, [])
    curves, grid = _write_figures(cfg, runs, out_dir, axes, row_keys, columns_by)
    search = search_curves(runs, out_dir / "search_curves.png", axes)
    for path in (curves, search, grid):
        if path is not None:
            files[path.name] = path
    figures = {"Learning curves": curves, SEARCH_HEADING: search, GRID_HEADING: grid}
    page = _page(name, runs, axes, tables, figures, warnings)
    files["index.html"] = atomic_write_text(out_dir / "index.html", page)
    return {
        "runs": len(runs),
        "out_dir": str(out_dir),
        "files": {k: str(v) for k, v in files.items()},
        "warnings": warnings,
    }


def _confounding_warnings(runs, axes: list[str], row_keys: list[str]) -> list[str]:
    """A warning (also logged) when the compared runs differ in more than the compared axes and seed."""
    warnings: list[str] = []
    differing = differing_params(runs, row_keys)
    if differing:
        msg = (
            f"the compared runs also differ in {', '.join(differing)} (besides "
            f"{', '.join(axes)} and the seed): the comparison is confounded"
        )
        log.warning("report: %s", msg)
        warnings.append(msg)
    return warnings


def _tables(runs, axes: list[str], row_keys: list[str], columns_by, metrics) -> dict[str, Any]:
    """{file stem: table}: quality and cost always, quality per spp and losses when the runs logged them."""
    if columns_by:
        comparison = per_value_table(runs, str(columns_by), axes, metrics)
    else:
        comparison = comparison_table(runs, axes, metrics)
    per_spp = comparison_table(runs, axes, metrics, group_by="spp")
    tables = {"comparison": comparison, "cost": cost_table(runs, axes)}
    if per_spp.attrs.get("metrics"):
        tables["comparison_per_spp"] = per_spp
    losses = loss_table(runs, row_keys)
    if losses.attrs.get("metrics"):
        tables["losses"] = losses
    return tables


def _tables_by_value(runs, axes: list[str], tables_by, metrics) -> dict[str, Any]:
    """{`comparison_<value>`: quality table of the runs with that value of config key `tables_by`}."""
    if not tables_by:
        return {}
    values = config_values(runs, str(tables_by))
    return {
        f"comparison_{_STEM_UNSAFE.sub('_', value)}": comparison_table(runs[values == value], axes, metrics)
        for value in dict.fromkeys(values)
    }


def _heading(stem: str) -> str:
    """The HTML heading of a table: its fixed heading, or `Quality: <value>` for a per-value table."""
    return TABLE_HEADINGS.get(stem) or f"Quality: {stem.removeprefix('comparison_')}"


def _write_tables(tables: dict[str, Any], out_dir: Path, warnings: list[str]) -> dict[str, Path]:
    """Each table as `<stem>.md`, `.tex` and `.csv` in `out_dir`, the warnings as notes."""
    files: dict[str, Path] = {}
    for stem, table in tables.items():
        files[f"{stem}.md"] = atomic_write_text(out_dir / f"{stem}.md", to_markdown(table, notes=warnings))
        files[f"{stem}.tex"] = atomic_write_text(out_dir / f"{stem}.tex", to_latex(table, notes=warnings))
        files[f"{stem}.csv"] = atomic_write_text(out_dir / f"{stem}.csv", to_csv(table, notes=warnings))
    return files


def _write_figures(cfg: Any, runs, out_dir: Path, axes: list[str], row_keys: list[str], columns_by):
    """The learning curves and the image grid (of one `columns_by` value); each None when not drawn."""
    rc = cfg.report
    crop_size, zoom = _crop(cfg)
    curves = learning_curves(runs, out_dir / "learning_curves.png", row_keys)
    n_images = int(config_value(rc, "images", DEFAULT_IMAGES))
    grid_runs = _first_value_only(runs, columns_by)
    grid = image_grid(grid_runs, out_dir / "image_grid.png", n_images, axes, crop_size, zoom)
    return curves, grid


def _page(
    name: str, runs, axes: list[str], tables: dict[str, Any], figures: dict, warnings: list[str]
) -> str:
    """The self-contained HTML page: the tables under their headings, the figures, the runs."""
    compared = ", ".join(axis_label(a) for a in axes)
    stamp = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    return render_html(
        title=f"nrbench report: {name}",
        subtitle=f"{len(runs)} MLflow runs from {mlflow.get_tracking_uri()}, compared by {compared}; "
        f"generated {stamp}. Values: mean ± std over runs (seeds) per row; best per column in bold.",
        tables={_heading(k): v for k, v in tables.items()},
        figures=figures,
        runs=runs,
        labels=run_labels(runs, axes),
        notes=warnings,
    )


def report_line(summary: dict) -> str:
    """The one line the report stage and the sweep callback print."""
    return f"report: {summary['runs']} runs -> {summary['out_dir']}/index.html"
