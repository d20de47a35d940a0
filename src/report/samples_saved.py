"""The samples-saved table: what a denoiser is worth in rendering time, from the per-image rows of the runs'
`eval/per_image.csv` (`collect.per_image_rows`) that carry the spp-equivalent (src/eval/scorers.py
`SppEquivalentScores`).

One row per compared row and noisy input count (`spp`): over every held-out image (a sequence counts once)
and every run (seed) of that row,

- `spp-equivalent`: the geometric mean of the samples per pixel a plain render needs to reach the output's
  error, with its `min` and `max`. Counts are ratios: the geometric mean is the one that a 2x above and a
  2x below average out in;
- `lower bounds`: the share of those values that are "at least" readings (past the ladder's top count or
  the reference's own noise); where it is above 0 the mean and the max are lower bounds too;
- `speed-up`: the geometric mean (and range) of the render time a plain render at the equivalent count
  takes over the input render plus the denoising (src/metrics/spp_equivalent.py `speedup`);
- `noisy reads`: the geometric mean of the noisy inputs' own equivalents, the check that the ladder reads
  a plain render at its own count (it should be near `spp`);
- `ladder residual`: the largest RMS log residual of the Monte Carlo law on the images' ladders;
- `images`: how many (image, run) values the row holds.
"""

from __future__ import annotations

import html
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from src.metrics.spp_equivalent import geometric_mean
from src.report.collect import DEFAULT_AXES
from src.report.site import html_table
from src.report.table_writers import cells, write_table_with_notes
from src.report.tables import RUNS_COLUMN, MetricSpec, axis_keys, axis_label

STEM = "samples_saved"
HEADING = "Samples saved: spp-equivalent and speed-up over rendering more samples"
REQUIRED = "metrics.spp_equivalent"
SPECS: dict[str, MetricSpec] = {
    "spp-equivalent": ("spp_equivalent", True, "{:.1f}"),
    "min": ("", None, "{:.1f}"),
    "max": ("", None, "{:.1f}"),
    "lower bounds": ("spp_equivalent_at_least", None, "{:.0%}"),
    "speed-up": ("speedup", True, "{:.2f}"),
    "speed-up min": ("", None, "{:.2f}"),
    "speed-up max": ("", None, "{:.2f}"),
    "noisy reads": ("noisy_spp_equivalent", None, "{:.1f}"),
    "ladder residual": ("ladder_residual", None, "{:.2f}"),
    "images": ("", None, "{:.0f}"),
}


def _row(group: pd.DataFrame) -> dict[str, float]:
    value = pd.to_numeric(group["metrics.spp_equivalent"])
    speed = pd.to_numeric(group["metrics.speedup"])
    return {
        "spp-equivalent": geometric_mean(value),
        "min": float(value.min()),
        "max": float(value.max()),
        "lower bounds": float(pd.to_numeric(group["metrics.spp_equivalent_at_least"]).mean()),
        "speed-up": geometric_mean(speed),
        "speed-up min": float(speed.min()),
        "speed-up max": float(speed.max()),
        "noisy reads": geometric_mean(pd.to_numeric(group["metrics.noisy_spp_equivalent"])),
        "ladder residual": float(pd.to_numeric(group["metrics.ladder_residual"]).max()),
        "images": float(value.notna().sum()),
        RUNS_COLUMN: group["run_id"].nunique() if "run_id" in group else 1,
    }


def samples_saved_table(images: pd.DataFrame, axes: Sequence[str] | None = None) -> pd.DataFrame | None:
    """Rows (axes..., spp) of the module docstring's columns; None when no image row has an equivalent."""
    if images.empty or REQUIRED not in images or images[REQUIRED].isna().all():
        return None
    images = images[images[REQUIRED].notna() | images["metrics.noisy_spp_equivalent"].notna()]
    axes = list(axes or DEFAULT_AXES)
    labels = [axis_label(a) for a in axes]
    keys = axis_keys(images, axes).assign(spp=images["spp"].astype(int))
    grouped = images.groupby([keys[k] for k in keys], sort=False)
    rows = {key: _row(group) for key, group in grouped}
    table = pd.DataFrame.from_dict(rows, orient="index")
    table.index = pd.MultiIndex.from_tuples(list(rows), names=[*labels, "spp"])
    table = table.sort_index(level="spp", sort_remaining=False, kind="stable")
    table.attrs = {"metrics": dict(SPECS), "axes": [*labels, "spp"]}
    return table


NOTES = [
    "spp-equivalent: samples per pixel a plain render needs to reach the output's error (geometric mean "
    "over held-out images and seeds, min and max); where 'lower bounds' > 0, the mean and max are lower "
    "bounds (past the ladder's top count or the reference's own noise)",
    "speed-up = spp-equivalent x render s/spp / (input spp x render s/spp + denoise s), per frame: render "
    "seconds from the ladder's renders, denoising seconds from the evaluation, on the devices the report's "
    "subtitle names; '-' where the ladder has no render time (a Noisebase set's, averaged from its stored "
    "samples)",
    "noisy reads: the noisy inputs' own equivalents, a check (near spp when the ladder reads a plain render "
    "at its own count); best values are marked within each spp; an undefined output (a GP expression's "
    "NaN weights) has no equivalent and is not among 'images': the quality tables' 'undefined' counts it",
]


def best_per_spp(table: pd.DataFrame) -> dict[str, set[int]]:
    """Per column with a direction, the row positions of its best value within each input count: counts
    apart are not compared (a denoiser fed more samples reads more)."""
    best: dict[str, set[int]] = {}
    frame = table.reset_index()
    for label, (_, higher, _) in table.attrs["metrics"].items():
        if higher is None:
            continue
        for _, part in frame.groupby("spp"):
            values = pd.to_numeric(part[label], errors="coerce").dropna()
            if values.nunique() < 2:
                continue
            target = values.max() if higher else values.min()
            best.setdefault(label, set()).update(int(i) for i, v in values.items() if v == target)
    return best


def write_samples_saved(table: pd.DataFrame, out_dir: Path, warnings: Sequence[str]) -> dict[str, Path]:
    """`samples_saved.{md,tex,csv}`: the table, the report's warnings above it, `NOTES` below."""
    return write_table_with_notes(STEM, table, out_dir, warnings, NOTES, best_per_spp(table))


def samples_saved_html(table: pd.DataFrame) -> str:
    """The table for the report page, best per input count in bold, `NOTES` under it."""
    header, _, rows = cells(table, best_per_spp(table))
    body = [
        [f"<b>{html.escape(text)}</b>" if bold else html.escape(text) for text, _, bold in row]
        for row in rows
    ]
    return html_table([html.escape(h) for h in header], body) + "".join(
        f"<p>{html.escape(n)}</p>" for n in NOTES
    )
