"""The Noisebase table: the runs scored with `metrics.protocol=noisebase` (src/eval/denoise_eval.py,
src/metrics/noisebase_protocol.py) in the layout of the Noisebase benchmark's results (Balint et al. 2023,
"Neural Partitioning Pyramids for Denoising Monte Carlo Renderings", SIGGRAPH; its `nb_result_table`):
one row per compared method and sample count, columns PSNR, SSIM, MS-SSIM, FVVDP (FovVideoVDP, JOD),
FLIP and tPSNR, each the mean over the held-out sequences of the per-sequence numbers (as their table
averages its per-sequence metric files), then mean ± std over seeds; and CVVDP where the runs logged it.

Published numbers sit in their own block, source `published`, never mixed with the measured rows (source
`measured`) and never marked best: the paper's NPPD at 4 spp on test8 (29.35 dB PSNR, 0.883 SSIM, 7.66
FovVideoVDP). The `noisebase` 1.1.1 package ships no results table, so these three numbers, quoted in
nrbench's issue 35 from the paper, are the only published ones here; the other cells of that row are "-".

CVVDP, ColorVideoVDP (Mantiuk et al. 2024; JOD, higher is better), is the table's optional colour video
column: only where a measured run logged `eval_cvvdp` (`metrics.cvvdp.enabled=true`), the `cvvdp`
package's version, the display and the frame rate in a note. It is not one of the protocol's numbers:
Noisebase scores no ColorVideoVDP, so it is nrbench's (src/metrics/cvvdp_metric.py: `metrics.tonemap`
frames, every frame), not computed on the protocol's 8-bit ACES frames after the warm-up, and no
published number sits beside it (docs/noisebase.md, "Scoring").
"""

from __future__ import annotations

import html
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from src.report.collect import DEFAULT_AXES
from src.report.site import html_table
from src.report.table_writers import cells, write_table_with_notes
from src.report.tables import RUNS_COLUMN, MetricSpec, aggregate, axis_label

STEM = "noisebase"
HEADING = "Noisebase protocol (Balint et al. 2023): measured here, then published"
SOURCE = "source"
MEASURED, PUBLISHED = "measured", "published"
#: label -> (MLflow metric key without its `_spp<N>`, higher is better, format), in Noisebase's order.
NOISEBASE_METRICS: dict[str, MetricSpec] = {
    "PSNR": ("eval_nb_psnr", True, "{:.2f}"),
    "SSIM": ("eval_nb_ssim", True, "{:.4f}"),
    "MS-SSIM": ("eval_nb_msssim", True, "{:.4f}"),
    "FVVDP": ("eval_nb_fvvdp", True, "{:.2f}"),
    "FLIP": ("eval_nb_flip", False, "{:.4f}"),
    "tPSNR": ("eval_nb_tpsnr", True, "{:.2f}"),
    "CVVDP": ("eval_cvvdp", True, "{:.2f}"),  # optional (OPTIONAL): not a protocol number (module docstring)
}
#: Columns shown only where a measured run logged them; they do not make a run a protocol run.
OPTIONAL = ("CVVDP",)
#: The published rows: (method, spp, {label: value}), Balint et al. 2023, test8.
PUBLISHED_ROWS: list[tuple[str, int, dict[str, float]]] = [
    ("NPPD (Balint et al. 2023, test8)", 4, {"PSNR": 29.35, "SSIM": 0.883, "FVVDP": 7.66}),
]
FVVDP_TAG = "tags.nrbench.noisebase.fvvdp"
VERSION_TAGS = ("noisebase", "pytorch-msssim", "pyfvvdp", "torch", "numpy")
CVVDP_VERSION_TAG = "tags.nrbench.cvvdp.version"


def _spps(runs: pd.DataFrame) -> list[int]:
    pattern = re.compile(r"^metrics\.eval_nb_[a-z]+_spp(\d+)$")
    return sorted(
        {int(m.group(1)) for c in runs.columns if (m := pattern.match(c)) and runs[c].notna().any()}
    )


def noisebase_table(runs: pd.DataFrame, axes: Sequence[str] | None = None) -> pd.DataFrame | None:
    """Rows (source, axes..., spp): the measured means per compared row and spp, then the published rows;
    None when no run logged the protocol's numbers. `attrs`: `metrics` (the columns), `notes` (versions,
    FovVideoVDP left out, the published rows' source) and `measured` (how many rows are measured)."""
    spps = _spps(runs)
    if not spps:
        return None
    axes = list(axes or DEFAULT_AXES)
    labels = [axis_label(a) for a in axes]
    parts = []
    for spp in spps:
        specs = {
            label: (f"{key}_spp{spp}", higher, fmt) for label, (key, higher, fmt) in NOISEBASE_METRICS.items()
        }
        protocol = [f"metrics.{k}" for label, (k, _, _) in specs.items() if label not in OPTIONAL]
        logged = runs[[c for c in protocol if c in runs]].notna().any(axis=1)
        frame = aggregate(runs[logged], axes, specs).reset_index()  # columns: the labels, `<label> std`
        frame.insert(0, SOURCE, MEASURED)
        frame["spp"] = spp
        parts.append(frame)
    measured = pd.concat(parts, ignore_index=True)
    shown = [label for label in NOISEBASE_METRICS if label not in OPTIONAL or label in measured]
    published = []
    for method, spp, values in PUBLISHED_ROWS:
        row: dict[str, Any] = {SOURCE: PUBLISHED, **dict.fromkeys(labels, ""), "spp": spp, RUNS_COLUMN: 0}
        row[labels[0]] = method
        row |= {label: values.get(label, float("nan")) for label in shown}
        published.append(row)
    out = pd.concat([measured, pd.DataFrame(published)], ignore_index=True)
    columns = [c for label in shown for c in (label, f"{label} std") if c in out] + [RUNS_COLUMN]
    out = out.set_index([SOURCE, *labels, "spp"])[columns]
    out.attrs = {
        "metrics": {label: NOISEBASE_METRICS[label] for label in shown},
        "notes": _notes(runs, "CVVDP" in shown),
        "measured": len(measured),
    }
    return out


def _values(runs: pd.DataFrame, column: str) -> str:
    """The distinct values the runs logged in `column`, joined with ' / ' ('?' when none did)."""
    found = sorted({str(v) for v in runs[column].dropna()}) if column in runs else []
    return " / ".join(found) or "?"


def _notes(runs: pd.DataFrame, cvvdp: bool) -> list[str]:
    notes = []
    versions = []
    for name in VERSION_TAGS:
        column = f"tags.nrbench.noisebase.{name}"
        if column in runs:
            found = sorted({str(v) for v in runs[column].dropna()})
            versions.append(f"{name} {' / '.join(found)}")
    if versions:
        notes.append("measured with " + ", ".join(versions))
    warmup = "params.metrics.noisebase.warmup"
    if warmup in runs:
        found = sorted({str(v) for v in runs[warmup].dropna()})
        notes.append(f"first {' / '.join(found)} frames of each sequence left unscored (Noisebase: 16)")
    if FVVDP_TAG in runs and (runs[FVVDP_TAG].astype(str) == "false").any():
        notes.append("FVVDP left out (metrics.noisebase.fvvdp=false) in some or all measured runs: '-' there")
    notes.append(
        "published: Balint et al. 2023 (NPPD, test8, 4 spp), as printed in the paper, not measured here; "
        "the noisebase package ships no results table, so cells it does not give are '-'"
    )
    if cvvdp:
        display = _values(runs, "params.metrics.cvvdp.display")
        fps, version = _values(runs, "params.metrics.cvvdp.fps"), _values(runs, CVVDP_VERSION_TAG)
        notes.append(
            f"CVVDP: ColorVideoVDP (Mantiuk et al. 2024, JOD, 10 = indistinguishable), cvvdp {version}, "
            f"display {display}, {fps} fps, on the metrics.tonemap frames, every frame: nrbench's, not a "
            "Noisebase protocol number (no 8-bit ACES, no warm-up, nothing published); '-' where a run had "
            "metrics.cvvdp.enabled=false"
        )
    else:
        notes.append("ColorVideoVDP (cvvdp): off in the runs (metrics.cvvdp.enabled=false): no column")
    return notes


def best_measured(table: pd.DataFrame) -> dict[str, set[int]]:
    """Per column, the measured rows holding the best mean among the measured rows of their spp (ties
    all); published rows are never best."""
    best: dict[str, set[int]] = {}
    frame = table.reset_index()
    measured = frame[frame[SOURCE] == MEASURED]
    for label, (_, higher, _) in table.attrs["metrics"].items():
        for _, part in measured.groupby("spp"):
            values = pd.to_numeric(part[label], errors="coerce").dropna()
            if higher is None or values.nunique() < 2:
                continue
            target = values.max() if higher else values.min()
            best.setdefault(label, set()).update(int(i) for i, v in values.items() if v == target)
    return best


def write_noisebase_table(table: pd.DataFrame, out_dir: Path, warnings: Sequence[str]) -> dict[str, Path]:
    """`noisebase.{md,tex,csv}`: the table, the report's warnings above it, its own notes below."""
    return write_table_with_notes(STEM, table, out_dir, warnings, table.attrs["notes"], best_measured(table))


def noisebase_html(table: pd.DataFrame) -> str:
    """The table for the report page (published rows in italics), its notes under it."""
    header, _, rows = cells(table, best_measured(table))
    body = []
    for row in rows:
        texts = []
        for mean, std, bold in row:
            text = html.escape(mean if std is None else f"{mean} ± {std}")
            texts.append(f"<b>{text}</b>" if bold else text)
        body.append(texts)
    classes = ["" if row[0][0] == MEASURED else "noisy" for row in rows]
    notes = "".join(f"<p>{html.escape(n)}</p>" for n in table.attrs["notes"])
    return html_table([html.escape(h) for h in header], body, classes) + notes
