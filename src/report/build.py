"""The `report` stage: tables, figures and an HTML page from the logged MLflow runs that `cfg.report`
selects, written to `<report.out_dir>/<report.name>/`:

    comparison.{md,tex,csv}           quality metrics per compared row (mean ± std over seeds)
    comparison_<value>.{md,tex,csv}   the same for one value of `report.tables_by` (e.g. one scene)
    comparison_per_spp.{md,tex,csv}   the same per noisy spp level (when the runs logged them)
    cost.{md,tex,csv}                 parameters, training time, iterations, inference time, and the cost
                                      card: FLOPs per pixel, achieved GFLOP/s and its fraction of the
                                      device's measured peak, peak host and GPU memory of train and eval
    losses.{md,tex,csv}               final validation and training loss per component (learned models)
    per_image.{md,tex,csv}            relMSE, relMSE / noisy, energy, PSNR per row and held-out image
                                      (the runs' eval/per_image.csv; denoising and filter evaluations)
    samples_saved.{md,tex,csv}        per row and noisy spp: the spp-equivalent (geometric mean, range, share
                                      of lower bounds) and the speed-up over rendering more samples, from
                                      the runs' per-image rows (src/report/samples_saved.py)
    paired.{md,tex,csv}               each row against the best row per metric, paired by seed and
                                      held-out image: ratio or difference, Wilcoxon p, significant or not (n)
    noisebase.{md,tex,csv}            runs scored with metrics.protocol=noisebase: spp rows x PSNR, SSIM,
                                      MS-SSIM, FVVDP, FLIP, tPSNR in Noisebase's layout, the published
                                      NPPD row in its own block (src/report/noisebase_table.py)
    feature_usage.{md,tex,csv}        task=filter_search: feature terminals of the runs' best expressions
    best_expressions.{md,csv}         task=filter_search: each run's best expression (infix) with its search
                                      fitness and its held-out numbers, best held-out first
    quality_vs_time.{md,tex,csv,png}  trainings: the validation metric against the training clock per row
                                      (median and seeds' range), seconds to reach the worst row's final
                                      value, value at the shortest row's training time
                                      (src/report/quality_time.py)
    learning_curves.png, image_grid.png, index.html (self-contained)
    search_curves.png                 task=filter_search: best fitness per generation, one curve per run
    report.json                       what the report site (src/report/site.py) lists: title, profiles,
                                      runs, date, tables, and per method its configs, size and times

The quality tables carry the noisy input as a row when the runs logged its scores; a report with
smoke-profile runs says at its top that their numbers mean nothing. Every file is written atomically,
then the site's index (`<out_dir>/index.html`) and method pages are rebuilt. When no run matches,
`DataError` names the filter that matched nothing and no file is written.
"""

from __future__ import annotations

import html
import json
import logging
import re
from collections.abc import Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import mlflow
import pandas as pd

from src.gp.text import compact
from src.io.atomic import atomic_write_text
from src.multirun import quiet_mlflow_logs
from src.report.collect import (
    DEFAULT_AXES,
    config_value,
    differing_params,
    find_runs,
    param_column,
    per_image_rows,
    store_name,
)
from src.report.cost_card import with_peak_fraction
from src.report.figures import (
    DEFAULT_CROP,
    DEFAULT_MIN_TILE,
    GRID_HEADINGS,
    TEMPORAL_HEADING,
    image_grid,
    learning_curves,
    quality_against_cost,
    quality_by_spp,
    run_labels,
    search_curves,
    temporal_grid,
)
from src.report.html import render_html
from src.report.noisebase_table import HEADING as NOISEBASE_HEADING
from src.report.noisebase_table import STEM as NOISEBASE_STEM
from src.report.noisebase_table import noisebase_html, noisebase_table, write_noisebase_table
from src.report.paired import paired_table
from src.report.quality_time import HEADING as TIME_HEADING
from src.report.quality_time import STEM as TIME_STEM
from src.report.quality_time import quality_against_time
from src.report.samples_saved import HEADING as SAVED_HEADING
from src.report.samples_saved import STEM as SAVED_STEM
from src.report.samples_saved import samples_saved_html, samples_saved_table, write_samples_saved
from src.report.site import MANIFEST, SMOKE, SMOKE_NOTE, html_table, method_file, refresh_site, relative
from src.report.table_writers import to_csv, to_latex, to_markdown, write_table_with_notes
from src.report.tables import (
    BEST_EXPRESSION_TAG,
    axis_label,
    comparison_table,
    config_values,
    cost_table,
    feature_usage_table,
    loss_table,
    measured_on,
    per_image_table,
    per_value_table,
    select_metrics,
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
    "quality_vs_time": "Quality against training time (mean ± std over seeds)",
}
SEARCH_HEADING = "Filter search: best fitness per generation"
EXPRESSIONS_HEADING = "Filter search: best expressions (infix), best held-out relMSE / noisy first"
_STEM_UNSAFE = re.compile(r"[^\w.-]")  # characters a per-value table's file name replaces by "_"
GRID_HEADING = GRID_HEADINGS["denoised"]
PROFILE_TAG = "tags.nrbench.profile"
#: The tag of the expression the filter-search eval scored on the held-out split (its run's eval_*
#: metrics); runs without an eval have only the search's best (`BEST_EXPRESSION_TAG`).
EVALUATED_EXPRESSION_TAG = "tags.search.evaluated_expression"
#: Held-out columns of the best-expressions table: label -> MLflow metric.
EXPRESSION_METRICS = {
    "search fitness (min)": "search_best_so_far",
    "held-out relMSE / noisy": "eval_relmse_ratio",
    "held-out relMSE (Bako)": "eval_relmse",
    "held-out PSNR": "eval_psnr",
    "held-out Energy": "eval_energy",
}
#: What each clock of the cost table covers: under the table and in the page's subtitle.
CLOCKS = (
    "Clocks: train time counts the training batches and optimiser steps (not validation, logging or data "
    "preparation); ms / image the method's call on an item already on the device (a denoiser's frames in "
    "tiles, a radiance field's view in ray chunks), after one untimed warm-up item (not loading, scoring or "
    "saving); GFLOP/s the useful FLOPs over "
    "that time; host and GPU MB the peak of each stage (host sampled every 50 ms, GPU from PyTorch's "
    "allocator)."
)
#: The run metrics a method page shows per report (means over the method's runs in the report).
METHOD_METRICS = (
    "param_count",
    "train_time_s",
    "eval_ms_per_image",
    "eval_ms_per_mpixel",
    "eval_spp_equivalent",
    "eval_speedup",
)


#: Defaults of optional `report:` keys for a config that lacks them (a hand-built one, e.g. in the tests);
#: conf/config.yaml sets every key (`name` is the task's name there).
DEFAULT_REPORT_NAME = "report"
DEFAULT_OUT_DIR = "reports"
DEFAULT_IMAGES = 3


#: The per-spp table drawn (quality against the noisy sample count): readable where the table runs wide.
SPP_HEADING = "Quality against sample count (mean over seeds, bars: their std)"
#: The quality and cost tables drawn together: what each method's quality costs in evaluation time.
COST_HEADING = "Quality against evaluation time per image (mean over seeds, bars: their std)"


def _crop(cfg: Any, runs=None) -> tuple[int, int]:
    """Crop size and zoom of the grid: what the drawn runs logged as `task.eval.crop_size` / `crop_zoom`
    (their evaluation's strips; the most common value where they differ), so that a job's report and a
    sweep's report, whatever profile the report itself composes, crop alike; else the config's
    `task.eval`; else `DEFAULT_CROP` (logged). A value that is not an integer is an error, not a silent
    default."""
    e = config_value(config_value(cfg, "task"), "eval")
    crop = []
    for key, default in zip(("crop_size", "crop_zoom"), DEFAULT_CROP, strict=True):
        value = _most_logged(runs, f"task.eval.{key}")
        value = config_value(e, key) if value is None else value
        if value is None:
            log.info("report: no task.eval.%s logged or configured; the image grid's is %d", key, default)
        crop.append(default if value is None else int(value))
    return crop[0], crop[1]


def _most_logged(runs, key: str) -> str | None:
    """The value the runs logged most often for config key `key` (a param), None when none logged it."""
    column = param_column(key)
    if runs is None or column not in runs or runs[column].isna().all():
        return None
    return str(runs[column].dropna().astype(str).value_counts().index[0])


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
    files = _write_tables({k: v for k, v in tables.items() if k != "cost"}, out_dir, warnings)
    files |= write_table_with_notes("cost", tables["cost"], out_dir, warnings, [CLOCKS])
    if (usage := feature_usage_table(runs)) is not None:  # no confounding notes: it compares no rows
        tables["feature_usage"] = usage
        files |= _write_tables({"feature_usage": usage}, out_dir, [])
    sections, section_tables = {}, {}
    if (saved := samples_saved_table(images, axes)) is not None:  # runs whose evaluation had a ladder
        files |= write_samples_saved(saved, out_dir, warnings)
        sections[SAVED_HEADING] = samples_saved_html(saved)
        section_tables[SAVED_STEM] = SAVED_HEADING
    if (noisebase := noisebase_table(runs, axes)) is not None:  # runs scored with metrics.protocol=noisebase
        files |= write_noisebase_table(noisebase, out_dir, warnings)
        sections[NOISEBASE_HEADING] = noisebase_html(noisebase)
        section_tables[NOISEBASE_STEM] = NOISEBASE_HEADING
    if (expressions := best_expressions(runs, axes)) is not None:
        files["best_expressions.csv"] = atomic_write_text(
            out_dir / "best_expressions.csv", expressions.to_csv(index=False)
        )
        files["best_expressions.md"] = atomic_write_text(
            out_dir / "best_expressions.md", _expressions_markdown(expressions)
        )
        sections[EXPRESSIONS_HEADING] = _expressions_html(expressions)
    curves, grid, temporal = _write_figures(cfg, runs, out_dir, axes, row_keys, columns_by)
    search = search_curves(runs, out_dir / "search_curves.png", axes)
    for path in (curves, search, grid and grid.path, temporal):
        if path is not None:
            files[path.name] = path
    time_png, time_table = quality_against_time(runs, out_dir / f"{TIME_STEM}.png", axes)
    if time_table is not None:  # trainings that logged their clock at each validation point
        tables[TIME_STEM] = time_table
        files |= write_table_with_notes(TIME_STEM, time_table, out_dir, warnings, time_table.attrs["notes"])
        files[time_png.name] = time_png
    grid_heading = grid.heading if grid is not None else GRID_HEADING
    per_spp = tables.get("comparison_per_spp")
    spp_png = quality_by_spp(per_spp, out_dir / "quality_by_spp.png") if per_spp is not None else None
    if spp_png is not None:
        files[spp_png.name] = spp_png
    cost_png = quality_against_cost(tables["comparison"], tables["cost"], out_dir / "quality_cost.png")
    if cost_png is not None:
        files[cost_png.name] = cost_png
    figures = {
        SPP_HEADING: spp_png,
        COST_HEADING: cost_png,
        "Learning curves": curves,
        TIME_HEADING: time_png,
        SEARCH_HEADING: search,
        grid_heading: grid and grid.path,
        TEMPORAL_HEADING: temporal,
    }
    root = Path(str(config_value(rc, "out_dir", DEFAULT_OUT_DIR))).expanduser()
    manifest = report_manifest(name, runs, axes, tables, config_value(rc, "experiment"), section_tables)
    page = _page(name, runs, axes, tables, figures, warnings, sections, manifest)
    files[MANIFEST] = atomic_write_text(out_dir / MANIFEST, json.dumps(manifest, indent=1) + "\n")
    files["index.html"] = atomic_write_text(out_dir / "index.html", page)
    if config_value(rc, "site", True):
        refresh_site(root, config_value(rc, "committed_ledger"))
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
    tables = {"comparison": comparison, "cost": cost_table(with_peak_fraction(runs), axes)}
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
    """The learning curves, the image grid and, for sequences, the crop through time (of one `columns_by`
    value); each None when not drawn."""
    rc = cfg.report
    curves = learning_curves(runs, out_dir / "learning_curves.png", row_keys)
    n_images = int(config_value(rc, "images", DEFAULT_IMAGES))
    grid_runs = _first_value_only(runs, columns_by)
    crop_size, zoom = _crop(cfg, grid_runs)
    min_tile = int(config_value(rc, "min_tile_px", DEFAULT_MIN_TILE))
    grid = image_grid(grid_runs, out_dir / "image_grid.png", n_images, axes, crop_size, zoom, min_tile)
    temporal = temporal_grid(grid_runs, out_dir / "temporal_strip.png", axes, crop_size, zoom, min_tile)
    return curves, grid, temporal


def _page(
    name: str,
    runs,
    axes: list[str],
    tables: dict[str, Any],
    figures: dict,
    warnings: list[str],
    sections: dict[str, str],
    manifest: dict[str, Any],
) -> str:
    """The self-contained HTML page: the smoke banner, the tables under their headings, the figures, the
    runs; links to the site's index and the method pages."""
    compared = ", ".join(axis_label(a) for a in axes)
    profiles = manifest["profiles"]
    smoke = runs[PROFILE_TAG] == SMOKE if PROFILE_TAG in runs else pd.Series(False, index=runs.index)
    banner = None
    if smoke.any():
        share = "" if smoke.all() else f" (smoke-profile runs here: {int(smoke.sum())} of {len(runs)})"
        banner = SMOKE_NOTE + share
    links = [f'<a href="{relative("index.html", name)}">All reports</a>']
    links += [
        f'<a href="{relative(method_file(m), name)}">{html.escape(m)}</a>'
        for m in sorted(manifest["methods"])
    ]
    return render_html(
        title=manifest["title"],
        subtitle=f"{len(runs)} MLflow runs ({', '.join(profiles) or 'no'} profile) from "
        f"{store_name(mlflow.get_tracking_uri())}, compared by {compared}; "
        f"generated {manifest['generated']}. Values: "
        "mean ± std over runs (seeds) per row; best per column in bold; the noisy input's row (italics), "
        f"where logged, is what a denoiser must beat and is never marked best. Timings measured on: "
        f"{measured_on(runs)}. {CLOCKS}",
        tables={_heading(k): v for k, v in tables.items()},
        figures=figures,
        runs=runs,
        labels=run_labels(runs, axes),
        notes=warnings,
        banner=banner,
        links=" · ".join(links[:1]) + (" · methods: " + ", ".join(links[1:]) if links[1:] else ""),
        sections=sections,
    )


def _mean(runs, column: str) -> float | None:
    if column not in runs:
        return None
    values = runs[column].dropna()
    return float(values.astype(float).mean()) if len(values) else None


def report_manifest(
    name: str,
    runs,
    axes: list[str],
    tables: dict[str, Any],
    experiment,
    section_tables: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """`report.json`: what the site lists about this report (src/report/site.py), from its runs only: the
    title, experiments, profiles (`nrbench.profile` tags), run count, date, tables (file stem: heading;
    `section_tables` adds those the page shows in a section of their own, e.g. the Noisebase table), and
    per method (`model.name`) its run count, distinct configurations (its `model.*` params) and the
    means of its `METHOD_METRICS`."""
    experiments = [str(e) for e in ([experiment] if isinstance(experiment, str) else list(experiment or []))]
    profiles = sorted({str(p) for p in runs[PROFILE_TAG].dropna()}) if PROFILE_TAG in runs else []
    methods: dict[str, Any] = {}
    if "params.model.name" in runs:
        model_columns = sorted(c for c in runs.columns if c.startswith("params.model."))
        for model, part in runs.groupby("params.model.name", sort=True):
            configs: dict[str, dict[str, Any]] = {}
            for _, run in part.iterrows():
                params = {
                    c.removeprefix("params."): str(run[c]) for c in model_columns if isinstance(run[c], str)
                }
                key = json.dumps(params, sort_keys=True)
                configs.setdefault(key, {"params": params, "runs": 0})["runs"] += 1
            methods[str(model)] = {
                "runs": len(part),
                "run_ids": [str(r) for r in part["run_id"]],
                "configs": list(configs.values()),
                **{m: _mean(part, f"metrics.{m}") for m in METHOD_METRICS},
            }
    headings = {stem: _heading(stem) for stem in tables} | dict(section_tables or {})
    if BEST_EXPRESSION_TAG in runs:
        headings["best_expressions"] = EXPRESSIONS_HEADING
    return {
        "name": name,
        "title": f"nrbench report: {name}",
        "experiments": experiments,
        "profiles": profiles,
        "runs": len(runs),
        "generated": datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC"),
        "tables": headings,
        "methods": methods,
    }


def best_expressions(runs, axes: list[str]):
    """task=filter_search: per run its label, the expression its eval scored on the held-out split (else
    the search's best, infix as the search logs it: src/gp/text.py::to_infix), the search's minimum
    fitness and the held-out numbers (`EXPRESSION_METRICS`), best held-out relMSE / noisy first (runs
    without one last, by fitness). None when no run logged an expression."""
    if BEST_EXPRESSION_TAG not in runs and EVALUATED_EXPRESSION_TAG not in runs:
        return None
    rows = []
    for label, (_, run) in zip(run_labels(runs, axes), runs.iterrows(), strict=True):
        evaluated = run.get(EVALUATED_EXPRESSION_TAG)
        expression = evaluated if isinstance(evaluated, str) else run.get(BEST_EXPRESSION_TAG)
        if not isinstance(expression, str):
            continue
        row = {"run": label, "seed": run.get("params.seed"), "expression": expression}
        row |= {k: run.get(f"metrics.{m}") for k, m in EXPRESSION_METRICS.items()}
        row["scored on"] = "held-out split" if isinstance(evaluated, str) else "search only (no eval)"
        rows.append(row)
    if not rows:
        return None
    frame = pd.DataFrame(rows)
    return frame.sort_values(
        ["held-out relMSE / noisy", "search fitness (min)"], na_position="last", kind="stable"
    ).reset_index(drop=True)


def _text(value) -> str:
    """A cell of the best-expressions table: numbers to 4 significant digits, "-" for none."""
    if isinstance(value, float):
        return "-" if value != value else f"{value:.4g}"
    return "-" if value is None else str(value)


def _shown(column: str, value) -> str:
    """A cell as the page and the Markdown show it: an expression with compact constants
    (src/gp/text.py::compact; the CSV keeps the logged text), other values as `_text`."""
    return compact(value) if column == "expression" and isinstance(value, str) else _text(value)


def _expressions_markdown(frame) -> str:
    lines = ["| " + " | ".join(frame.columns) + " |", "|" + "---|" * len(frame.columns)]
    for row in frame.itertuples(index=False):
        cells = (_shown(c, v).replace("|", "\\|") for c, v in zip(frame.columns, row, strict=True))
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _expressions_html(frame) -> str:
    """The best-expressions table: numbers to 4 significant digits, expressions as code (compact)."""

    def cell(column: str, value) -> str:
        text = html.escape(_shown(column, value))
        return f"<code>{text}</code>" if column == "expression" else text

    rows = [
        [cell(c, v) for c, v in zip(frame.columns, row, strict=True)] for row in frame.itertuples(index=False)
    ]
    return '<div class="plain">' + html_table([html.escape(c) for c in frame.columns], rows) + "</div>"


def report_line(summary: dict) -> str:
    """The one line the report stage and the sweep callback print."""
    return f"report: {summary['runs']} runs -> {summary['out_dir']}/index.html"
