"""Comparison and cost tables from MLflow runs (written by `src/report/table_writers.py`; the paired table
of a study is `src/report/paired.py`'s).

A table is a DataFrame with one row per distinct value of the compared axes (index, named by the axes'
display labels, e.g. `model`), and per metric label `L` the columns `L` (mean over the row's runs, i.e.
over seeds), `L std` (sample std; NaN with one run) and one `runs` column (how many runs each row
aggregates). `table.attrs["metrics"]` keeps, per label, (MLflow metric key, higher_is_better, format);
higher_is_better None means "no best value" (e.g. iteration counts).
"""

from __future__ import annotations

import logging
import re
from collections import Counter
from collections.abc import Mapping, Sequence

import pandas as pd

from src.errors import ConfigError
from src.report.collect import DEFAULT_AXES, param_column

log = logging.getLogger("nrbench.report")

#: label -> (MLflow metric key, higher is better, format)
MetricSpec = tuple[str, bool | None, str]

COMPARISON_METRICS: dict[str, MetricSpec] = {
    "PSNR": ("eval_psnr", True, "{:.2f}"),
    "SSIM": ("eval_ssim", True, "{:.4f}"),
    "LPIPS": ("eval_lpips", False, "{:.4f}"),
    "relMSE (Bako)": ("eval_relmse", False, "{:.4g}"),  # mean over pixels and RGB, eps metrics.relmse_eps
    "relMSE (Eq. 3.5)": ("eval_relmse_spp", False, "{:.4g}"),  # GP thesis: RGB sum x spp/2 (denoising)
    "relMSE / noisy": ("eval_relmse_ratio", False, "{:.4g}"),  # the GP thesis's fitness term
    "FLIP": ("eval_flip", False, "{:.4f}"),
    # mean(output) / mean(reference) on linear HDR, the truth 1.0 (src/metrics/image.py::energy): a filter
    # that darkens the image can still lower relMSE (issue 32); neither higher nor lower is better.
    "Energy": ("eval_energy", None, "{:.4f}"),
    # Sequences (dataset=volumetric): mean |Δt output - Δt reference|, tone-mapped (src/metrics/temporal.py)
    "Flicker": ("eval_temporal", False, "{:.4g}"),
    # Noisebase's temporal PSNR (Balint et al. 2023): PSNR of Δt output against Δt reference, per frame pair
    # then averaged, tone-mapped, peak 1 (src/metrics/temporal.py::temporal_psnr)
    "tPSNR": ("eval_tpsnr", True, "{:.2f}"),
    # RMS flicker against the noise-free truth from two independent references (no floor; negative: within
    # the estimate's noise of the truth); only runs on data with a second reference log it, else "-"
    "Flicker vs truth": ("eval_flicker_unbiased", False, "{:.4g}"),
    # ColorVideoVDP (Mantiuk et al. 2024) of each sequence, JOD (10: indistinguishable from the reference),
    # tone-mapped frames on an SDR display model (src/metrics/cvvdp_metric.py); only runs with
    # metrics.cvvdp.enabled=true log it, else "-"
    "CVVDP": ("eval_cvvdp", True, "{:.2f}"),
    # the share of held-out frames whose output is undefined (a searched GP expression's NaN/Inf weights
    # or zero weight sum there, src/models/filters/gp_filter.py): the other columns average the rest
    "Undefined": ("eval_undefined", False, "{:.3g}"),
    # the constant-sigma cross-bilateral filter the filter search scores beside its expression on the
    # same held-out images (task.eval.baseline, conf/task/filter_search.yaml)
    "baseline relMSE / noisy": ("eval_baseline_relmse_ratio", False, "{:.4g}"),
    "baseline PSNR": ("eval_baseline_psnr", True, "{:.2f}"),
    # task=filter_search: fitness = mean relMSE(filtered) / relMSE(noisy) on the search images (Davletaliyev
    # 2016, Eq. 3.5), logged per generation (MLflow keeps the last): the last generation's best, and the
    # minimum over all generations (its Sec. 4.2 measure; with a hall of fame, the default, the expression
    # evaluated on the test split; without one, the last generation's best is).
    "best fitness": ("search_best", False, "{:.4g}"),
    "min fitness": ("search_best_so_far", False, "{:.4g}"),
}
COST_METRICS: dict[str, MetricSpec] = {
    "params": ("param_count", False, "{:,.0f}"),
    "train time (s)": ("train_time_s", False, "{:.1f}"),
    "iterations": ("steps", None, "{:,.0f}"),
    # task=filter_search: the search alone (not its evaluation), src/tasks/filter_search.py
    "search time (s)": ("search_seconds", False, "{:.1f}"),
    "ms / image": ("eval_ms_per_image", False, "{:.1f}"),
    "ms / MP": ("eval_ms_per_mpixel", False, "{:.1f}"),
    # the cost card (issue 46): FLOPs of one output pixel, achieved GFLOP/s at eval and its fraction of the
    # device's measured peak (src/report/cost_card.py), peak memory of the training and eval stages
    "FLOPs / px": ("eval_flops_per_pixel", None, "{:,.0f}"),
    "FLOPs / ray": ("eval_flops_per_ray", None, "{:,.0f}"),  # NeRF: MLP forward, nominal samples
    "GFLOP/s (eval)": ("eval_gflops", True, "{:.2f}"),
    "of peak": ("eval_peak_fraction", True, "{:.1%}"),
    "host MB (train)": ("train_peak_host_mb", False, "{:,.0f}"),
    "host MB (eval)": ("eval_peak_host_mb", False, "{:,.0f}"),
    "GPU MB (train)": ("train_peak_device_mb", False, "{:,.0f}"),
    "GPU MB (eval)": ("eval_peak_device_mb", False, "{:,.0f}"),
}
LPIPS_VARIANT_TAG = "tags.nrbench.lpips_variant"
RUNS_COLUMN = "runs"
#: One line under a table for each column a reader could misread, keyed by the column's label or the
#: start of it ("baseline" covers "baseline PSNR", "Energy" covers "Energy 4spp"). LPIPS: `_lpips_note`.
COLUMN_NOTES = {
    "Energy": "Energy: mean output / mean reference on linear HDR; 1 is right (below: darker, above: "
    "brighter).",
    "baseline": "baseline: the constant-sigma cross-bilateral filter (task.eval.baseline), scored on the "
    "same held-out images as the method of its row.",
    "relMSE (Bako)": "relMSE (Bako): mean over pixels and RGB of (output - reference)^2 / (reference^2 + "
    "eps).",
    "relMSE (Eq. 3.5)": "relMSE (Eq. 3.5): the filter-search thesis's relMSE (RGB sum, times spp / 2).",
    "relMSE / noisy": "relMSE / noisy: the output's relMSE over the noisy input's (below 1: the filter "
    "helps).",
    "Undefined": "Undefined: the share of held-out frames whose output is undefined; the other columns "
    "average the rest.",
    "Flicker vs truth": "Flicker vs truth: RMS flicker against the noise-free truth (negative: within the "
    "estimate's noise).",
    "CVVDP": "CVVDP: ColorVideoVDP in JOD (10: indistinguishable from the reference).",
    "of peak": "of peak: achieved GFLOP/s over the device's measured peak.",
    RUNS_COLUMN: "runs: the runs (training seeds) a row averages; ± is their sample standard deviation.",
}


def _lpips_note(label: str) -> str:
    """What an LPIPS column can be compared with: on a random trunk it is a harness-internal distance."""
    if "random" in label:
        return (
            "LPIPS: here on a VGG trunk with random weights (no pretrained weights were given): it ranks the "
            "rows of this table and is not comparable with published LPIPS values."
        )
    return "LPIPS: learned perceptual distance (Zhang et al. 2018) with the weights named in its label."


def column_legend(columns: Sequence[str]) -> list[str]:
    """The notes (`COLUMN_NOTES`, LPIPS by its variant) for the columns of a table, once each, in column
    order."""
    lines: dict[str, None] = {}
    for column in map(str, columns):
        if column.startswith("LPIPS"):
            lines[_lpips_note(column)] = None
        for key, note in COLUMN_NOTES.items():
            if column == key or column.startswith(f"{key} "):
                lines[note] = None
    return list(lines)


#: The text of a value that is not there: an axis param a run did not log (its own row, not dropped), or a
#: metric no run of a row logged (NaN mean, e.g. a model that does not log FLIP); never shown as 0.
MISSING = "-"


def select_metrics(labels: Sequence[str] | None) -> dict[str, MetricSpec]:
    """The quality columns `report.metrics` names, in its order (all of COMPARISON_METRICS when None)."""
    if labels is None:
        return dict(COMPARISON_METRICS)
    labels = [str(label) for label in labels]
    if not labels or any(label not in COMPARISON_METRICS for label in labels):
        raise ConfigError(f"report.metrics={labels}: expected labels among {list(COMPARISON_METRICS)}")
    return {label: COMPARISON_METRICS[label] for label in labels}


def config_values(runs: pd.DataFrame, key: str) -> pd.Series:
    """Each run's value of config key `key` as text (MISSING where a run did not log it)."""
    column = param_column(key)
    return (
        runs[column].fillna(MISSING).astype(str) if column in runs else pd.Series(MISSING, index=runs.index)
    )


def axis_label(axis: str) -> str:
    """Display label of a compared config key: `model.name` -> `model`, `task.train.lr` -> `task.train.lr`."""
    key = param_column(axis).split(".", 1)[1]
    return key.removesuffix(".name") if key.endswith(".name") else key


def _lpips_label(runs: pd.DataFrame) -> str:
    """`LPIPS (<variant>[, <variant>...])` naming the LPIPS network variant(s) the runs logged."""
    if LPIPS_VARIANT_TAG not in runs:
        return "LPIPS"
    variants = sorted({str(v) for v in runs[LPIPS_VARIANT_TAG].dropna() if str(v)})
    return f"LPIPS ({', '.join(variants)})" if variants else "LPIPS"


def per_spp_metrics(runs: pd.DataFrame, metrics: Mapping[str, MetricSpec]) -> dict[str, MetricSpec]:
    """Per-spp columns `"<label> <N>spp"` for every `eval_<metric>_spp<N>` key the runs logged."""
    out: dict[str, MetricSpec] = {}
    for label, (key, higher, fmt) in metrics.items():
        pattern = re.compile(rf"^metrics\.{re.escape(key)}_spp(\d+)$")
        spps = sorted({int(m.group(1)) for c in runs.columns if (m := pattern.match(c))})
        for spp in spps:
            out[f"{label} {spp}spp"] = (f"{key}_spp{spp}", higher, fmt)
    return out


#: Metrics whose column is shown only where some run has a nonzero value: the share of undefined outputs
#: is 0 for every method but a searched GP expression, and a column of zeros says nothing.
ONLY_NONZERO = {"eval_undefined"}


def _shown(values: pd.Series, key: str) -> bool:
    """Whether a metric's column is shown: some run logged it (and, for `ONLY_NONZERO`, not as 0)."""
    if key in ONLY_NONZERO:
        return bool((pd.to_numeric(values).fillna(0) != 0).any())
    return bool(values.notna().any())


def axis_keys(runs: pd.DataFrame, axes: Sequence[str]) -> pd.DataFrame:
    """Each row's value of each axis as text, one column per axis label (`MISSING` where a run did not log
    the axis): what the tables group rows by."""
    return pd.DataFrame(
        {
            axis_label(a): runs[c].fillna(MISSING).astype(str)
            if c in runs
            else pd.Series(MISSING, index=runs.index)
            for a, c in ((a, param_column(a)) for a in axes)
        },
        index=runs.index,
    )


def aggregate(runs: pd.DataFrame, axes: Sequence[str], metrics: Mapping[str, MetricSpec]) -> pd.DataFrame:
    """Mean, std and count per distinct axis value, rows in order of first appearance."""
    labels = [axis_label(a) for a in axes]
    keys = axis_keys(runs, axes)
    present = {lab: spec for lab, spec in metrics.items() if f"metrics.{spec[0]}" in runs}
    present = {lab: spec for lab, spec in present.items() if _shown(runs[f"metrics.{spec[0]}"], spec[0])}
    values = pd.DataFrame({lab: pd.to_numeric(runs[f"metrics.{spec[0]}"]) for lab, spec in present.items()})
    values = values.reindex(runs.index)
    grouped = values.groupby([keys[lab] for lab in labels], sort=False, dropna=False)
    mean, std = grouped.mean(), grouped.std(ddof=1)
    counts = keys.groupby(labels, sort=False).size()
    table = pd.DataFrame(index=counts.index)
    for label in present:
        table[label] = mean[label]  # every present label is a column of `values`; NaN where a row lacks it
        table[f"{label} std"] = std[label]
    table[RUNS_COLUMN] = counts
    table.attrs["metrics"] = dict(present)
    table.attrs["axes"] = labels
    return table


#: The row of a quality table that holds the noisy input's scores (the `eval_noisy_*` metrics the denoising
#: evaluation logs beside each output's, src/eval/denoise_eval.py): what a denoiser must beat. It is no
#: compared method: never the best of a column, never a row of the paired table, no method page.
NOISY_ROW = "noisy input"


def noisy_key(key: str) -> str:
    """The metric key of the noisy input's score beside an output's: `eval_psnr` -> `eval_noisy_psnr`,
    `eval_psnr_spp4` -> `eval_noisy_psnr_spp4`, a per-image score `relmse` -> `noisy_relmse`."""
    return f"eval_noisy_{key.removeprefix('eval_')}" if key.startswith("eval_") else f"noisy_{key}"


def with_noisy_row(
    table: pd.DataFrame, frame: pd.DataFrame, axes: Sequence[str], keep: Sequence[str] = ()
) -> pd.DataFrame:
    """`table` (built by `aggregate` from `frame` over `axes`) with the noisy input's scores as rows on
    top: its first axis `NOISY_ROW`, the other axes blank but those in `keep` (e.g. the held-out image of
    the per-image table: one noisy row per image). Each cell is the mean over the runs (or image rows) that
    logged the noisy score of the column's metric (`noisy_key`); a std only where they differ (runs on
    different data). `table` unchanged when no run logged any noisy score (NeRF, cost tables)."""
    specs = metric_specs(table)
    columns = {label: f"metrics.{noisy_key(key)}" for label, (key, _, _) in specs.items() if key}
    columns = {label: c for label, c in columns.items() if c in frame and frame[c].notna().any()}
    if not columns:
        return table
    logged = frame[list(columns.values())].notna().any(axis=1)
    pseudo = pd.DataFrame(index=frame.index[logged])
    for i, axis in enumerate(axes):
        column = param_column(axis)
        if axis in keep and column in frame:
            pseudo[column] = frame.loc[logged, column]
        else:
            pseudo[column] = NOISY_ROW if i == 0 else ""
    for label, column in columns.items():
        pseudo[f"metrics.{specs[label][0]}"] = pd.to_numeric(frame.loc[logged, column])
    noisy = aggregate(pseudo, axes, {label: specs[label] for label in columns})
    for label in columns:  # identical data give identical noisy scores: a std of 0 is no spread
        std = noisy[f"{label} std"]
        noisy[f"{label} std"] = std.where(std.abs() > 1e-9 * noisy[label].abs())
    out = pd.concat([noisy, table]).reindex(columns=table.columns)
    out.attrs = dict(table.attrs)
    return out


def comparison_table(
    runs: pd.DataFrame,
    axes: Sequence[str] | None = None,
    metrics: Mapping[str, MetricSpec] | None = None,
    group_by: str | None = None,
    noisy: bool = True,
) -> pd.DataFrame:
    """Quality metrics per distinct value of `axes` (default `model.name`), mean ± std over seeds.

    `group_by="spp"` gives one column per metric and noisy spp (`eval_<metric>_spp<N>` keys); any other
    value is a config key added to the rows (e.g. `dataset.name`). Metrics no run logged are dropped;
    the LPIPS label names the variant(s) in the runs' `nrbench.lpips_variant` tags. With `noisy`, the
    noisy input's scores come first as their own row (`with_noisy_row`) when the runs logged them.
    """
    axes = list(axes or DEFAULT_AXES)
    metrics = dict(COMPARISON_METRICS if metrics is None else metrics)
    if "LPIPS" in metrics:
        metrics = {(_lpips_label(runs) if k == "LPIPS" else k): v for k, v in metrics.items()}
    if group_by == "spp":
        metrics = per_spp_metrics(runs, metrics)
    elif group_by:
        axes.append(group_by)
    table = aggregate(runs, axes, metrics)
    return with_noisy_row(table, runs, axes) if noisy else table


def per_value_table(
    runs: pd.DataFrame,
    column_key: str,
    axes: Sequence[str] | None = None,
    metrics: Mapping[str, MetricSpec] | None = None,
) -> pd.DataFrame:
    """Quality metrics with one column per metric and value of config key `column_key` (e.g.
    `task.scene`: "PSNR spheres", "PSNR busy", ...), rows per distinct value of `axes`: the per-scene
    layout of the NeRF papers' tables. Values are means ± std over the runs (seeds) of a row and value."""
    axes = list(axes or DEFAULT_AXES)
    values = config_values(runs, column_key)
    parts = []
    for value in dict.fromkeys(values):
        part = comparison_table(runs[values == value], axes, metrics)
        rename = {
            c: f"{c.removesuffix(' std')} {value}" + (" std" if c.endswith(" std") else "") for c in part
        }
        part.attrs["metrics"] = {f"{label} {value}": spec for label, spec in part.attrs["metrics"].items()}
        rename[RUNS_COLUMN] = f"{RUNS_COLUMN} {value}"
        parts.append(part.rename(columns=rename))
    table = pd.concat(parts, axis=1)
    table.attrs["metrics"] = {k: v for part in parts for k, v in part.attrs["metrics"].items()}
    table.attrs["axes"] = parts[0].attrs["axes"]
    # One runs column (the total per row), as in the other tables.
    counts = [c for c in table.columns if c.startswith(f"{RUNS_COLUMN} ")]
    # NaN in a "runs <value>" column: that row has no run with that value, i.e. 0 runs (exact, not a guess).
    table[RUNS_COLUMN] = table[counts].fillna(0).sum(axis=1).astype(int)
    return table.drop(columns=counts)


_LOSS_KEY = re.compile(r"^metrics\.(val|train)_loss_(\w+)$")


def loss_metrics(runs: pd.DataFrame) -> dict[str, MetricSpec]:
    """`"val <component>"`, then `"train <component>"`, for every per-epoch (or per-validation) loss the
    runs logged (`val_loss_<c>`, `train_loss_<c>`; MLflow keeps the last value): the final losses the
    seed thesis compares its ablations on (e.g. the specular loss with and without whitening)."""
    found = [m.groups() for c in runs.columns if (m := _LOSS_KEY.match(c))]
    ordered = sorted(found, key=lambda split_component: (split_component[0] != "val", split_component[1]))
    return {f"{split} {c}": (f"{split}_loss_{c}", False, "{:.4g}") for split, c in ordered}


def loss_table(runs: pd.DataFrame, axes: Sequence[str] | None = None) -> pd.DataFrame:
    """Final validation and training losses per component (`loss_metrics`), mean ± std over seeds; rows
    of methods that train nothing (filters, OIDN: no loss logged) are left out, not shown as dashes."""
    table = aggregate(runs, list(axes or DEFAULT_AXES), loss_metrics(runs))
    labels = list(table.attrs.get("metrics", {}))
    if not labels:
        return table
    trained = table[table[labels].notna().any(axis=1)]
    trained.attrs = table.attrs
    return trained


#: The run tags of the device card (`src.train.device.device_card`, `precision`), in the order stated.
DEVICE_TAGS = ("tags.nrbench.device_name", "tags.nrbench.threads", "tags.nrbench.precision")


def measured_on(runs: pd.DataFrame) -> str:
    """What the runs' timings were measured on, each distinct device card with its run count: `AMD EPYC,
    2 threads, fp32 (4 runs)`; runs logged before runs carried the card read `<device>, model and
    threads not recorded`."""
    if runs.empty:
        return "no runs"

    def card(row: pd.Series) -> str:
        name, threads, precision = (row.get(t) for t in DEVICE_TAGS)
        if not isinstance(name, str) or not name:
            device = row.get("tags.nrbench.device")
            device = device if isinstance(device, str) and device else "device"
            return f"{device}, model and threads not recorded" + (
                f", {precision}" if isinstance(precision, str) and precision else ""
            )
        return f"{name}, {threads} threads, {precision}"

    counts = runs.apply(card, axis=1).value_counts(sort=False)
    return "; ".join(f"{c} ({n} run{'s' if n != 1 else ''})" for c, n in counts.items())


#: The cost card's columns of `COST_METRICS` that `run_costs` states (work, throughput, memory).
CARD_COLUMNS = (
    "FLOPs / px",
    "FLOPs / ray",
    "GFLOP/s (eval)",
    "host MB (train)",
    "host MB (eval)",
    "GPU MB (train)",
    "GPU MB (eval)",
)


def run_costs(runs: pd.DataFrame) -> str:
    """The runs' cost card beyond the device: the median over the runs of each `CARD_COLUMNS` value they
    logged (`FLOPs / px 385,794, GFLOP/s (eval) 190.00, host MB (eval) 1,512`; the median, as one slow run
    should not move the card), or that none was logged (runs older than the cost card)."""
    parts = []
    for label in CARD_COLUMNS:
        key, _, fmt = COST_METRICS[label]
        column = f"metrics.{key}"
        if column not in runs:
            continue
        values = pd.to_numeric(runs[column], errors="coerce").dropna()
        if len(values):
            parts.append(f"{label} {fmt.format(float(values.median()))}")
    return "median " + ", ".join(parts) if parts else "FLOPs and memory not logged"


def cost_table(runs: pd.DataFrame, axes: Sequence[str] | None = None) -> pd.DataFrame:
    """Parameters, training or search time, iterations and inference time (per image and per megapixel)."""
    return aggregate(runs, list(axes or DEFAULT_AXES), COST_METRICS)


#: The columns of the per-image table (`per_image_table`): the scores of `eval/per_image.csv` by label.
PER_IMAGE_METRICS: dict[str, MetricSpec] = {
    "relMSE (Bako)": ("relmse", False, "{:.4g}"),
    "relMSE / noisy": ("relmse_ratio", False, "{:.4g}"),
    "Energy": ("energy", None, "{:.4f}"),
    "noisy Energy": ("noisy_energy", None, "{:.4f}"),
    "PSNR": ("psnr", True, "{:.2f}"),
}
IMAGE_AXIS = "image"


def per_image_table(images: pd.DataFrame, axes: Sequence[str] | None = None) -> pd.DataFrame | None:
    """Scores per compared row and held-out image (`<scene> <spp>spp`), mean ± std over the runs (seeds)
    of that row, from the rows of the runs' `eval/per_image.csv` (`collect.per_image_rows`): a mean over
    two test images can rest on one of them (issue 32), so the denoisers' and filters' reports show each
    image's relMSE and energy beside the means of the comparison table. None when no run has the file."""
    if images.empty:
        return None
    images = images.assign(
        **{param_column(IMAGE_AXIS): images["scene"].astype(str) + " " + images["spp"].astype(str) + "spp"}
    )
    axes = [*(axes or DEFAULT_AXES), IMAGE_AXIS]
    return with_noisy_row(aggregate(images, axes, PER_IMAGE_METRICS), images, axes, keep=[IMAGE_AXIS])


BEST_EXPRESSION_TAG = "tags.search.best_expression"
FEATURE_USAGE_METRICS: dict[str, MetricSpec] = {
    "occurrences": ("", None, "{:,.0f}"),
    "share": ("", None, "{:.3f}"),
}


def feature_usage_table(runs: pd.DataFrame) -> pd.DataFrame | None:
    """Feature terminals of the runs' best expressions (tag `search.best_expression`, task=filter_search):
    per feature its `occurrences` (nodes, summed over the runs), their `share` of all feature occurrences,
    and `runs` (how many best expressions read it); most frequent first (Davletaliyev 2016, Figure 4.8:
    "frequencies of occurrences of different features"). None when no run has a parsable expression."""
    if BEST_EXPRESSION_TAG not in runs:
        return None
    from src.gp.run_metrics import feature_counts  # the GP grammar loads torch: only for search runs

    total: Counter[str] = Counter()
    used: Counter[str] = Counter()
    for expression in runs[BEST_EXPRESSION_TAG].dropna():
        try:
            counts = feature_counts(str(expression))
        except Exception as err:  # e.g. a tag cut at its 4000 characters: that run is left out, logged
            log.warning("report: cannot parse a best expression (%s); left out of feature_usage", err)
            continue
        total.update(counts)
        used.update(counts.keys())
    if not total:
        return None
    order = sorted(total, key=lambda f: (-total[f], f))
    all_occurrences = sum(total.values())
    table = pd.DataFrame(
        {
            "occurrences": [float(total[f]) for f in order],
            "share": [total[f] / all_occurrences for f in order],
            RUNS_COLUMN: [used[f] for f in order],
        },
        index=pd.Index(order, name="feature"),
    )
    table.attrs["metrics"] = dict(FEATURE_USAGE_METRICS)
    table.attrs["axes"] = ["feature"]
    return table


# ------------------------------------------------------------------------------------------ cells


# -------------------------------------------------------------------------------------- renderers


def metric_specs(table: pd.DataFrame) -> dict[str, MetricSpec]:
    """`table.attrs["metrics"]`; a `ValueError` when absent (pandas operations such as merge drop attrs),
    instead of rendering the table silently without its metric columns."""
    if "metrics" not in table.attrs:
        raise ValueError(
            "table.attrs['metrics'] is missing: build tables with comparison_table / per_value_table / "
            "cost_table / loss_table and keep their attrs"
        )
    return table.attrs["metrics"]
