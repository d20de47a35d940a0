"""Report figures from MLflow runs: learning curves (metric histories), the filter search's best fitness per
generation (`search_curves`), and an image comparison grid (the tone-mapped `eval/png/*.png` artifacts each
evaluated run logs).

Each returns the written PNG's path, or None (with a log line) when the runs lack what they need, so a
report over baseline-only runs (no training curves) or runs without images still completes.
"""

from __future__ import annotations

import logging
import math
import re
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NamedTuple

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import mlflow  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.ticker import FuncFormatter, LogLocator, MaxNLocator, NullFormatter  # noqa: E402
from mlflow.tracking import MlflowClient  # noqa: E402
from PIL import Image  # noqa: E402

from src.io.atomic import atomic_path  # noqa: E402
from src.io.images import (  # noqa: E402
    SEPARATOR_PX,
    SEPARATOR_RGB,
    comparison_strip,
    temporal_strip,
    window_size,
    write_png,
)
from src.report.collect import param_column  # noqa: E402
from src.report.tables import DEFAULT_AXES, MISSING, NOISY_ROW  # noqa: E402

log = logging.getLogger("nrbench.report")

#: Loss components drawn first when present (denoisers; then NeRF levels); any others follow by name.
COMPONENT_ORDER = ("diffuse", "specular", "color", "coarse", "fine")
_LOSS_COLUMN = re.compile(r"^metrics\.(?:train|val)_loss_(?P<component>.+)$")


def save_figure(fig, out_png: str | Path) -> Path:
    """`fig` written atomically as a PNG at 110 dpi with a tight box (no label cut at the canvas edge),
    then closed; returns the path."""
    out_png = Path(out_png)
    with atomic_path(out_png) as tmp:
        fig.savefig(tmp, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return out_png


#: The noisy input's colour in every plot of a report: black (dashed where drawn as a line), outside the
#: cycle the methods share (tab10's eighth colour is a grey, so a grey would be taken by a method).
NOISY_COLOR = "#000000"


def row_colors(rows: Sequence[str]) -> dict[str, Any]:
    """One colour per compared row, the same in every plot of a report (quality against sample count and
    against cost; the learning curves' arms take the cycle in the same order): the noisy input black, the
    methods the colour cycle in row order (tab20 when they outnumber it)."""
    methods = [r for r in rows if r != NOISY_ROW]
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colors = plt.get_cmap("tab20").colors if len(methods) > len(cycle) else cycle
    out: dict[str, Any] = {r: colors[i % len(colors)] for i, r in enumerate(methods)}
    return out | ({NOISY_ROW: NOISY_COLOR} if NOISY_ROW in rows else {})


def row_name(index) -> str:
    """A table row's label: its index values joined by `/` (one value as it is)."""
    return "/".join(map(str, index)) if isinstance(index, tuple) else str(index)


def loss_components(runs: pd.DataFrame) -> list[str]:
    """The `<c>` of every `train_loss_<c>` / `val_loss_<c>` metric the runs logged, in display order."""
    found = {m["component"] for c in runs.columns if (m := _LOSS_COLUMN.match(c))}
    first = [c for c in COMPONENT_ORDER if c in found]
    return first + sorted(found - set(first))


PNG_DIR = "eval/png"
# `<image>-<kind>.png`: denoising images are `<scene>-<NNNNN>spp`, NeRF test views `<scene>-r_<i>`.
_PNG_NAME = re.compile(r"^(?P<name>.+?)-(?P<kind>noisy|denoised|rendered|reference)\.png$")
_SPP = re.compile(r"-(?P<spp>\d+)spp$")
#: The kinds that hold a method's output (denoised image, rendered view), in order of preference.
OUTPUT_KINDS = ("denoised", "rendered")


def _spp(name: str) -> int:
    match = _SPP.search(name)
    return int(match["spp"]) if match else 0


def _output_kind(kinds: set[str]) -> str | None:
    return next((k for k in OUTPUT_KINDS if k in kinds), None)


def arm_labels(runs: pd.DataFrame, axes: Sequence[str] | None = None) -> list[str]:
    """One label per run naming its arm: its axis values joined by `/` (`key=value` for an axis other
    than a name, e.g. `whiten=True`); the seeds of one arm share it."""
    axes = list(axes or DEFAULT_AXES)
    out = []
    for _, run in runs.iterrows():
        parts = []
        for axis in axes:
            v = run.get(param_column(axis))
            text = MISSING if v is None or (isinstance(v, float) and np.isnan(v)) else str(v)  # unlogged axis
            parts.append(text if axis.endswith(".name") else f"{axis.rsplit('.', 1)[-1]}={text}")
        out.append("/".join(parts))
    return out


def run_labels(runs: pd.DataFrame, axes: Sequence[str] | None = None) -> list[str]:
    """One label per run: its arm (`arm_labels`), plus `seed=N` where labels would repeat."""
    base = arm_labels(runs, axes)
    counts = pd.Series(base).value_counts()
    out = []
    for label, (_, run) in zip(base, runs.iterrows(), strict=True):
        seed = run.get("params.seed")  # a run without a logged seed gets no suffix (its label may repeat)
        out.append(f"{label} seed={seed}" if counts[label] > 1 and isinstance(seed, str) else label)
    return out


def arm_curve(series: Sequence[tuple[Sequence[int], Sequence[float]]]) -> tuple[np.ndarray, ...]:
    """(steps, mean, low, high) of one curve over an arm's seeds (`series`: each seed's steps and values):
    the steps every seed logged (all steps when they share none), the mean over seeds and the band from
    the lowest to the highest seed at each step."""
    columns = [pd.Series(list(ys), index=list(xs)).groupby(level=0).last() for xs, ys in series]
    frame = pd.concat(columns, axis=1).sort_index()
    shared = frame.dropna()
    frame = shared if len(shared) else frame
    return (
        frame.index.to_numpy(),
        frame.mean(axis=1).to_numpy(),
        frame.min(axis=1).to_numpy(),
        frame.max(axis=1).to_numpy(),
    )


def component_title(component: str) -> str:
    """A loss panel's title: "diffuse loss"; a component already named a loss keeps its name ("loss")."""
    return component if component.endswith("loss") else f"{component} loss"


def _history(client: MlflowClient, run_id: str, key: str) -> tuple[list[int], list[float]]:
    points = sorted(client.get_metric_history(run_id, key), key=lambda m: (m.step, m.timestamp))
    return [m.step for m in points], [m.value for m in points]


#: The curves of one loss component: (metric prefix, line style, alpha, legend suffix). Denoisers log a
#: loss per `log_every` steps (`train_step_loss_*`, drawn faint, as the seed thesis plots per-minibatch
#: losses) and epoch means of train and validation; NeRF logs its train losses per step.
CURVES = (("train_step", "-", 0.3, "per step"), ("train", "-", 1.0, "train"), ("val", "--", 1.0, "val"))


def curve_series(client: MlflowClient, run_id: str, component: str) -> list[tuple[str, list, list]]:
    """The (curve name, steps, values) of every curve of `component` the run logged, positive and finite
    values only (the axes are logarithmic)."""
    series = []
    for name, *_ in CURVES:
        steps, values = _history(client, run_id, f"{name}_loss_{component}")
        positive = [(s, v) for s, v in zip(steps, values, strict=True) if v > 0 and np.isfinite(v)]
        if positive:
            xs, ys = zip(*positive, strict=True)
            series.append((name, list(xs), list(ys)))
    return series


def learning_curves(
    runs: pd.DataFrame, out_png: str | Path, axes: Sequence[str] | None = None
) -> Path | None:
    """Per arm (the seeds of one compared setting, `arm_labels`), one colour: the mean over its seeds of
    the per-step (faint), train (solid) and validation (dashed) losses (`CURVES`) against the optimiser
    step, with a band from its lowest to its highest seed; one panel per component, log-scale y; the
    legend beside the panels (one entry per arm, then the line styles). None when no run logged any."""
    components = loss_components(runs)
    if not components:
        log.info("report: no run logged train_loss_*/val_loss_* histories; no learning curves")
        return None
    client = MlflowClient()
    arms: dict[str, list[str]] = {}
    for label, run_id in zip(arm_labels(runs, axes), runs["run_id"], strict=True):
        arms.setdefault(label, []).append(run_id)
    fig, panels = plt.subplots(
        1, len(components), figsize=(5 * len(components), 3.8), squeeze=False, layout="constrained"
    )
    colors = row_colors(list(arms))  # the arms' colours in the quality plots too
    handles = []
    for label, run_ids in arms.items():
        color = colors[label]
        drawn = _draw_arm(client, panels[0], components, run_ids, color)
        if drawn:
            seeds = f" ({len(run_ids)} seeds)" if len(run_ids) > 1 else ""
            handles.append(plt.Line2D([], [], color=color, lw=2, label=f"{label}{seeds}"))
    if not handles:
        plt.close(fig)
        log.info("report: no run logged train_loss_*/val_loss_* histories; no learning curves")
        return None
    for ax, component in zip(panels[0], components, strict=True):
        ax.set_yscale("log")
        ax.set_title(component_title(component))
        ax.set_xlabel("optimiser step")
        ax.grid(True, which="both", alpha=0.3)
    panels[0][0].set_ylabel("loss (mean over seeds; band: lowest to highest seed)")
    handles += [
        plt.Line2D([], [], color="#555", ls=style, alpha=alpha, label=suffix)
        for _, style, alpha, suffix in CURVES
    ]
    panels[0][-1].legend(
        handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize="small", frameon=False
    )
    return save_figure(fig, out_png)


def _draw_arm(client: MlflowClient, axes, components: Sequence[str], run_ids: Sequence[str], color) -> int:
    """One arm's curves (mean line and min-max band over its runs) on each component's axes; returns
    how many curves were drawn."""
    drawn = 0
    for ax, component in zip(axes, components, strict=True):
        by_curve: dict[str, list] = {}
        for run_id in run_ids:
            for name, xs, ys in curve_series(client, run_id, component):
                by_curve.setdefault(name, []).append((xs, ys))
        for name, series in by_curve.items():
            _, style, alpha, _ = next(c for c in CURVES if c[0] == name)
            steps, mean, low, high = arm_curve(series)
            marker = "." if len(steps) < 30 and alpha == 1.0 else None
            ax.plot(steps, mean, style, color=color, alpha=alpha, marker=marker)
            if len(series) > 1:
                ax.fill_between(steps, low, high, color=color, alpha=0.15 * alpha, lw=0)
            drawn += 1
    return drawn


#: Panels per row of the quality-against-sample-count figure.
SPP_PANELS_PER_ROW = 3
_PER_SPP_COLUMN = re.compile(r"^(?P<label>.+) (?P<spp>\d+)spp$")


def spp_series(table: pd.DataFrame) -> dict[str, dict[str, tuple[list[int], list[float], list[float]]]]:
    """{metric label: {row label: (spp counts, means, stds)}} of a per-spp quality table (columns
    `<label> <N>spp` and `<label> <N>spp std`, rows the compared arms), counts ascending; a row's missing
    values are left out."""
    out: dict[str, dict[str, tuple[list[int], list[float], list[float]]]] = {}
    for column in table.columns:
        match = _PER_SPP_COLUMN.match(str(column))
        if match is None:
            continue
        label, spp = match["label"], int(match["spp"])
        for index, value in table[column].items():
            if pd.isna(value):
                continue
            row = row_name(index)
            std = table.get(f"{column} std", pd.Series(dtype=float)).get(index, np.nan)
            xs, ys, es = out.setdefault(label, {}).setdefault(row, ([], [], []))
            xs.append(spp), ys.append(float(value)), es.append(0.0 if pd.isna(std) else float(std))
    for rows in out.values():
        for row, (xs, ys, es) in rows.items():
            order = np.argsort(xs)
            rows[row] = ([xs[i] for i in order], [ys[i] for i in order], [es[i] for i in order])
    return out


def _varies(by_row: dict[str, tuple[list[int], list[float], list[float]]]) -> bool:
    """Whether a metric's per-spp series hold more than one mean, or any spread over seeds."""
    means = {y for _, ys, _ in by_row.values() for y in ys}
    return len(means) > 1 or any(e > 0 for _, _, es in by_row.values() for e in es)


def quality_by_spp(table: pd.DataFrame, out_png: str | Path) -> Path | None:
    """The per-spp quality table as a figure: one panel per metric, the noisy sample count on a log2
    axis, one line per compared row (mean over its seeds, bars: their std), the legend beside the
    panels. A metric with one value everywhere (no undefined output at any count: 0) gets no panel; the
    table shows it. None without per-spp columns."""
    series = {label: by_row for label, by_row in spp_series(table).items() if _varies(by_row)}
    if not series:
        return None
    n_cols = min(len(series), SPP_PANELS_PER_ROW)  # rows of panels, never a strip too wide to read
    n_rows = math.ceil(len(series) / n_cols)
    fig, grid = plt.subplots(
        n_rows, n_cols, figsize=(4.2 * n_cols, 3.4 * n_rows), squeeze=False, layout="constrained"
    )
    for ax in grid.flat[len(series) :]:
        ax.set_visible(False)
    panels = [list(grid.flat[: len(series)])]
    colors = row_colors(list(dict.fromkeys(row for by_row in series.values() for row in by_row)))
    for ax, (label, by_row) in zip(panels[0], series.items(), strict=True):
        for row, (xs, ys, es) in by_row.items():
            ls = "--" if row == NOISY_ROW else "-"
            ax.errorbar(xs, ys, yerr=es, color=colors[row], ls=ls, marker="o", ms=4, capsize=2, label=row)
        ax.set_xscale("log", base=2)
        ax.set_xlabel("noisy samples per pixel")
        ax.set_title(label)
        ax.grid(True, which="both", alpha=0.3)
    handles, names = panels[0][0].get_legend_handles_labels()
    seen = dict(zip(names, handles, strict=True))
    for ax in panels[0][1:]:
        for handle, name in zip(*ax.get_legend_handles_labels(), strict=True):
            seen.setdefault(name, handle)
    grid[0][-1].legend(
        seen.values(), seen.keys(), loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False
    )
    return save_figure(fig, out_png)


#: The cost axis of the quality-against-cost figure (a column of the cost table) and the quality columns
#: drawn against it, those of the comparison table that are present.
COST_AXIS = "ms / image"
COST_QUALITY = ("PSNR", "relMSE / noisy", "SSIM")


#: Markers of the quality-against-cost points, with the colour telling rows apart where markers repeat.
COST_MARKERS = ("o", "s", "D", "^", "v", "P", "X")
#: Above this ratio of the slowest to the fastest time, the cost axis is logarithmic. On a narrower range a
#: log axis labels its minor ticks (12, 12.01, 12.02 ...) over each other.
COST_LOG_RATIO = 10


def cost_points(comparison: pd.DataFrame, cost: pd.DataFrame) -> dict[str, pd.DataFrame]:
    """{quality label: rows with columns cost, value, std} for each `COST_QUALITY` label of the comparison
    table, over the rows that have both a quality and a `COST_AXIS` value (the noisy input has no time)."""
    if COST_AXIS not in cost:
        return {}
    out = {}
    for label in COST_QUALITY:
        if label not in comparison:
            continue
        std = comparison.get(f"{label} std", pd.Series(np.nan, index=comparison.index))
        frame = pd.DataFrame({"value": comparison[label], "std": std}).join(cost[COST_AXIS].rename("cost"))
        frame = frame.dropna(subset=["value", "cost"])
        if len(frame):
            out[label] = frame[["cost", "value", "std"]]
    return out


def quality_against_cost(comparison: pd.DataFrame, cost: pd.DataFrame, out_png: str | Path) -> Path | None:
    """Each compared row's quality (mean over seeds, bars: std) against its evaluation time per image,
    one panel per quality metric; a colour and marker per row, named in one legend beside the panels (names
    written at the points would cover each other where two methods cost and score alike). None when no
    row has both."""
    points = cost_points(comparison, cost)
    if not points:
        return None
    fig, axes = plt.subplots(
        1, len(points), figsize=(4.6 * len(points), 3.6), squeeze=False, layout="constrained"
    )
    rows = list(dict.fromkeys(row for frame in points.values() for row in frame.index))
    colors = row_colors(rows)
    style = {row: (colors[row], COST_MARKERS[i % len(COST_MARKERS)]) for i, row in enumerate(rows)}
    for ax, (label, frame) in zip(axes[0], points.items(), strict=True):
        for row, point in frame.iterrows():
            color, marker = style[row]
            ax.errorbar(
                point["cost"],
                point["value"],
                yerr=0 if pd.isna(point["std"]) else point["std"],
                fmt=marker,
                color=color,
                capsize=2,
                label=row_name(row),
            )
        logarithmic = frame["cost"].max() / frame["cost"].min() > COST_LOG_RATIO
        if logarithmic:  # methods from a filter to a network span decades; a narrow range stays linear
            ax.set_xscale("log")
            # Plain numbers at 1, 2 and 5 per decade over up to two decades, else at the powers of ten:
            # the default labels minor ticks over each other on a range of about one decade.
            decades = np.log10(frame["cost"].max() / frame["cost"].min())
            ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0) if decades <= 2 else (1.0,)))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
            ax.xaxis.set_minor_formatter(NullFormatter())
        ax.set_xlabel(f"{COST_AXIS} (log)" if logarithmic else COST_AXIS)
        ax.set_title(label)
        ax.grid(True, which="both", alpha=0.3)
    handles = [
        plt.Line2D([], [], ls="", color=color, marker=marker, label=row_name(row))
        for row, (color, marker) in style.items()
    ]
    axes[0][-1].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), frameon=False)
    return save_figure(fig, out_png)


SEARCH_METRIC = "search_best"


def search_curves(runs: pd.DataFrame, out_png: str | Path, axes: Sequence[str] | None = None) -> Path | None:
    """The fitness (relMSE(filtered) / relMSE(noisy), Davletaliyev 2016, Eq. 3.5) of each task=filter_search
    run against the generation, one colour per run: solid the minimum so far (the thesis's measure in its
    Figure 4.6, relMSE against the number of iterations, Sec. 4.2), faint the generation's best
    (`search_best`, which may rise again). None when no run logged `search_best`."""
    if f"metrics.{SEARCH_METRIC}" not in runs or runs[f"metrics.{SEARCH_METRIC}"].isna().all():
        log.info("report: no run logged %s; no search curves", SEARCH_METRIC)
        return None
    client = MlflowClient()
    fig, ax = plt.subplots(figsize=(6.5, 4.2), layout="constrained")
    # 20 distinct colours: a sweep's 12 runs (4 settings x 3 seeds) must not share one.
    cycle = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    colors = plt.get_cmap("tab20").colors if len(runs) > len(cycle) else cycle
    plotted: list[float] = []
    for i, (label, run_id) in enumerate(zip(run_labels(runs, axes), runs["run_id"], strict=True)):
        steps, values = _history(client, run_id, SEARCH_METRIC)
        if steps:
            color, marker = colors[i % len(colors)], "." if len(steps) < 30 else None
            ax.plot(steps, np.minimum.accumulate(values), color=color, marker=marker, label=label)
            ax.plot(steps, values, color=color, alpha=0.3)
            plotted += values
    if not plotted:
        plt.close(fig)
        return None
    ax.set_xlabel("generation")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel("relMSE(filtered) / relMSE(noisy)\n(solid: minimum so far, faint: generation's best)")
    finite = [v for v in plotted if 0 < v < float("inf")]
    if finite and max(finite) / min(finite) > 10:  # a seed near 1, searched filters near 0.03: keep both
        ax.set_yscale("log")
    ax.grid(True, which="both", alpha=0.3)
    # Beside the axes, not on them: a sweep's dozen long run labels would hide the curves.
    ax.legend(fontsize="small", frameon=False, loc="upper left", bbox_to_anchor=(1.02, 1.0))
    return save_figure(fig, out_png)


def _png_names(client: MlflowClient, run_id: str) -> dict[str, set[str]]:
    """{image name (`<scene>-<NNNNN>spp`, `<scene>-r_<i>`): kinds present} from a run's `eval/png`."""
    out: dict[str, set[str]] = {}
    try:
        entries = client.list_artifacts(run_id, PNG_DIR)
    except Exception as err:  # an unreachable artifact store: skip this run, do not fail the report
        log.warning("report: cannot list %s of run %s (%s)", PNG_DIR, run_id, err)
        return out
    for entry in entries:
        match = _PNG_NAME.match(Path(entry.path).name)
        if match:
            out.setdefault(match["name"], set()).add(match["kind"])
    return out


def _load(run_id: str, name: str, dst: Path) -> np.ndarray:
    local = mlflow.artifacts.download_artifacts(
        run_id=run_id, artifact_path=f"{PNG_DIR}/{name}", dst_path=str(dst)
    )
    with Image.open(local) as image:
        return np.asarray(image.convert("RGB"), dtype=np.uint8)


def _pick(names: Sequence[str], max_images: int) -> list[str]:
    """Up to `max_images` names, one per scene first (lowest spp / first view), then further ones."""
    by_scene: dict[str, list[str]] = {}
    for name in sorted(names, key=lambda n: (n.rsplit("-", 1)[0], _spp(n))):
        by_scene.setdefault(name.rsplit("-", 1)[0], []).append(name)
    order = []
    depth = max((len(v) for v in by_scene.values()), default=0)
    for level in range(depth):
        order += [v[level] for v in by_scene.values() if level < len(v)]
    return order[:max_images]


#: The image grid's zoomed crop (side in pixels, zoom factor) when the task's eval config has none:
#: conf/task/denoise.yaml's `crop_size` / `crop_zoom`. task=nerf has no such keys; its grid gets the same.
DEFAULT_CROP = (32, 4)


#: The grid's heading by the kind of output its panels show, in the panels' order: a denoiser's grid starts
#: at its input, a radiance field's (which has none) at the reference it is to match.
GRID_HEADINGS = {
    "denoised": "Test images (noisy | denoised | reference; each tile's PSNR against the reference)",
    "rendered": "Test views (reference | rendered; each tile's PSNR against the reference)",
}


class Grid(NamedTuple):
    path: Path
    heading: str


#: The image grid's smallest tile side in pixels when the report config has none (`report.min_tile_px`).
DEFAULT_MIN_TILE = 256


def upscale_factor(shape: tuple[int, int], min_tile: int) -> int:
    """The whole factor that brings an (h, w) tile's short side to at least `min_tile` (1: already)."""
    return max(1, math.ceil(min_tile / max(1, min(shape))))


def upscaled(image: np.ndarray, k: int) -> np.ndarray:
    """`image` (H, W, C) enlarged k times by repeating each pixel (nearest neighbour)."""
    return image if k == 1 else np.repeat(np.repeat(image, k, axis=0), k, axis=1)


def crop_zoom(tile_width: int, crop_side: int, zoom: int, k: int) -> int:
    """The zoom of a grid's crop row, its tiles enlarged k times: at least the configured `zoom` of the
    original pixels (ceil(zoom / k) on the enlarged tile), and enough for the crop to fill its tile's
    width (a crop half as wide as its tile left the other half of the row blank)."""
    return max(1, math.ceil(zoom / k), tile_width // max(crop_side, 1))


def tile_psnr(tile: np.ndarray, reference: np.ndarray) -> float:
    """PSNR (dB) of a grid tile against the reference tile, on the 8-bit tone-mapped PNGs the grid shows
    (peak 1 after /255: src/metrics/image.py::psnr's formula, 10 log10(1 / MSE), here in numpy so the
    report does not import torch; +inf for a copy of the reference)."""
    mse = float(np.mean((tile.astype(np.float64) / 255.0 - reference.astype(np.float64) / 255.0) ** 2))
    return 10.0 * np.log10(1.0 / mse) if mse > 0 else float("inf")


def _with_psnr(label: str, value: float) -> str:
    return f"{label} {value:.2f} dB" if np.isfinite(value) else f"{label} (= reference)"


def image_grid(
    runs: pd.DataFrame,
    out_png: str | Path,
    max_images: int = 3,
    axes: Sequence[str] | None = None,
    crop_size: int = DEFAULT_CROP[0],
    zoom: int = DEFAULT_CROP[1],
    min_tile: int = DEFAULT_MIN_TILE,
) -> Grid | None:
    """For up to `max_images` test images: noisy (when logged) | each compared row's denoised image |
    reference, or, for rendered views, reference | each row's view, with a zoomed crop row (around the
    largest first-vs-last panel error), one strip per image stacked vertically; every tile but the
    reference labelled with its PSNR (`tile_psnr`). One run per distinct label (the first, e.g. the lowest
    seed). Tiles smaller than `min_tile` pixels on their short side are enlarged by a whole factor k,
    nearest neighbour (a pixel stays a block, never a blur), the crop then covering the same region
    (crop_size * k) at a zoom of at least `zoom`, and as wide as its tile (`crop_zoom`): a run's report and
    a sweep's show the same tiles. Runs
    without the `eval/png` artifacts are left out (logged); None when no run has them, else the PNG's
    path and its heading (`GRID_HEADINGS`)."""
    chosen = _runs_with_images(runs, axes)
    if not chosen:
        log.info("report: no run has %s artifacts; no image grid", PNG_DIR)
        return None
    common = set.intersection(*(set(names) for _, names in chosen.values()))
    _, first_names = next(iter(chosen.values()))
    common = {n for n in common if "reference" in first_names[n]}
    if not common:
        log.info("report: the runs share no test image with a reference PNG; no image grid")
        return None
    strips, kinds = [], set()
    with tempfile.TemporaryDirectory(prefix="nrbench-report-") as tmp:
        for name in _pick(sorted(common), max(int(max_images), 1)):
            panels = _panels(name, chosen, Path(tmp))
            if len({p[1].shape for p in panels}) != 1:
                log.warning("report: %s differs in size across runs; left out of the image grid", name)
                continue
            k = upscale_factor(panels[0][1].shape[:2], min_tile)
            panels = [(label, upscaled(image, k)) for label, image in panels]
            h, w = panels[0][1].shape[:2]
            side = min(crop_size * k, h, w)  # the crop window, clamped to the image as comparison_strip does
            strips.append(comparison_strip(panels, crop_size * k, crop_zoom(w, side, zoom, k)))
            kinds.add(_output_kind(first_names[name]))
    if not strips:
        return None
    heading = GRID_HEADINGS["denoised" if "denoised" in kinds else "rendered"]
    return Grid(write_png(out_png, _stack_strips(strips)), heading)


def _runs_with_images(
    runs: pd.DataFrame, axes: Sequence[str] | None
) -> dict[str, tuple[str, dict[str, set[str]]]]:
    """{row label without the seed: (run id, {image name: kinds})} of the first run per label that logged
    output PNGs; the others are left out (logged)."""
    client = MlflowClient()
    labels = run_labels(runs, axes)
    chosen: dict[str, tuple[str, dict[str, set[str]]]] = {}
    for label, run_id in zip(labels, runs["run_id"], strict=True):
        short = label.split(" seed=")[0]
        if short in chosen:
            continue
        names = {n: k for n, k in _png_names(client, run_id).items() if _output_kind(k)}
        if not names:
            log.info(
                "report: run %s (%s) has no %s images; left out of the image grid", run_id, short, PNG_DIR
            )
            continue
        chosen[short] = (run_id, names)
    return chosen


def _panels(
    name: str, chosen: dict[str, tuple[str, dict[str, set[str]]]], tmp: Path
) -> list[tuple[str, np.ndarray]]:
    """(label, image) panels of test image `name`: noisy (when the first run logged it), each chosen run's
    output, then the reference (the first run's); rendered views (no noisy input) put the reference
    first. Each label but the reference's ends in the tile's PSNR against the reference."""
    first_id, first_names = next(iter(chosen.values()))
    reference = _load(first_id, f"{name}-reference.png", tmp / "r")
    panels = []
    if "noisy" in first_names[name]:
        noisy = _load(first_id, f"{name}-noisy.png", tmp / "n")
        panels.append((_with_psnr(f"noisy {_spp(name)} spp", tile_psnr(noisy, reference)), noisy))
    for short, (run_id, names) in chosen.items():
        output = _load(run_id, f"{name}-{_output_kind(names[name])}.png", tmp / run_id)
        panels.append((_with_psnr(short, tile_psnr(output, reference)), output))
    frame = _SEQUENCE_NAME.match(name)
    label = f"reference, frame {int(frame['frame'])}" if frame else "reference"  # which frame of a sequence
    if _output_kind(first_names[name]) == "rendered":
        return [(label, reference), *panels]
    return [*panels, (label, reference)]


#: A sequence frame's image name: `<scene>-f<FFFF>-<NNNNN>spp` (src/eval/denoise_eval.py).
_SEQUENCE_NAME = re.compile(r"^(?P<scene>.+)-f(?P<frame>\d{4})-(?P<spp>\d+)spp$")
TEMPORAL_HEADING = "A crop through time (rows: noisy, each method, reference; columns: frames)"


def sequence_frames(names: Sequence[str]) -> list[str]:
    """The frame names of the first sequence (by scene, lowest sample count) with two frames or more, in
    frame order; [] when `names` hold no sequence."""
    groups: dict[tuple[str, int], list[tuple[int, str]]] = {}
    for name in names:
        if match := _SEQUENCE_NAME.match(name):
            groups.setdefault((match["scene"], int(match["spp"])), []).append((int(match["frame"]), name))
    for key in sorted(groups):
        if len(groups[key]) > 1:
            return [name for _, name in sorted(groups[key])]
    return []


def temporal_grid(
    runs: pd.DataFrame,
    out_png: str | Path,
    axes: Sequence[str] | None = None,
    crop_size: int = DEFAULT_CROP[0],
    zoom: int = DEFAULT_CROP[1],
    min_tile: int = DEFAULT_MIN_TILE,
) -> Path | None:
    """For sequence evaluations: one crop followed through the frames of the first held-out sequence
    (`src.io.images.temporal_strip`), a row for the noisy input, each compared row's output and the
    reference, each cell at least `min_tile / 2` pixels (the zoom raised for a small crop); None for still
    images or without PNGs."""
    chosen = _runs_with_images(runs, axes)
    if not chosen:
        return None
    common = set.intersection(*(set(names) for _, names in chosen.values()))
    first_id, first_names = next(iter(chosen.values()))
    frames = sequence_frames(sorted(n for n in common if "reference" in first_names[n]))
    if not frames:
        return None
    with tempfile.TemporaryDirectory(prefix="nrbench-report-") as tmp:
        tmp = Path(tmp)
        rows = []
        if all("noisy" in first_names[n] for n in frames):
            rows.append(("noisy", [_load(first_id, f"{n}-noisy.png", tmp / "n") for n in frames]))
        for short, (run_id, names) in chosen.items():
            rows.append(
                (short, [_load(run_id, f"{n}-{_output_kind(names[n])}.png", tmp / run_id) for n in frames])
            )
        rows.append(("reference", [_load(first_id, f"{n}-reference.png", tmp / "r") for n in frames]))
    # a cell at least half a grid tile (`min_tile`): a small image's crop is enlarged further
    ch, cw = window_size(crop_size, *rows[0][1][0].shape[:2])
    zoom = max(zoom, math.ceil(min_tile / 2 / min(ch, cw)))
    return write_png(out_png, temporal_strip(rows, crop_size, zoom))


def _stack_strips(strips: list[np.ndarray]) -> np.ndarray:
    """The strips one above the other, padded to the widest, with separator gaps between them."""
    width = max(s.shape[1] for s in strips)
    gap = np.full((SEPARATOR_PX * 2, width, 3), SEPARATOR_RGB, np.uint8)
    rows = []
    for strip in strips:
        pad = np.full((strip.shape[0], width - strip.shape[1], 3), SEPARATOR_RGB, np.uint8)
        rows += [np.concatenate([strip, pad], axis=1), gap]
    return np.concatenate(rows[:-1], axis=0)
