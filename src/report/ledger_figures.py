"""The ledger's two figures, drawn from its rows (`ledger_page.COLUMNS`, numbers as strings or floats):

- `status_chart`: the findings and readings of each source document, one stacked bar per document, a
  segment per status (the headline's counts, split by document);
- `forest_plot`: each claim that has an interval, its estimate and interval on the scale the ledger
  prints (a factor for log claims on a log axis; a difference in the metric's units otherwise, one
  panel per metric), the line of no difference, the published size (a diamond) and a comparable
  claim's tolerance (a band), coloured by status.

Each returns PNG bytes, or None when there is nothing to draw (no claim ran, or none has an interval).
Text stays inside the canvas (`bbox_inches="tight"`); the legend sits outside the axes.
"""

from __future__ import annotations

import io
import math

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402
from matplotlib.lines import Line2D  # noqa: E402

from src.report.claims import TALLIED  # noqa: E402
from src.report.verdicts import NOT_RUN, STATUSES  # noqa: E402

#: Table cells and chart segments of each status (pastel: black text stays readable on them).
STATUS_FILL = {
    "reproduced": "#d4edda",
    "direction only": "#fff3cd",
    "not reproduced": "#f8d7da",
    "not distinguishable": "#e2e3e5",
    "underpowered": "#e7f1ff",
    "confounded": "#f3d9fa",
    "not run": "#ffffff",
}
#: The forest plot's markers and interval lines (the same hues, dark enough on white).
STATUS_INK = {
    "reproduced": "#2e7d32",
    "direction only": "#a07800",
    "not reproduced": "#c62828",
    "not distinguishable": "#616161",
    "underpowered": "#1565c0",
    "confounded": "#8e24aa",
    "not run": "#000000",
}
DPI = 100
WIDTH_IN = 11.0  # 1,100 px at DPI: inside the site's 1,200-px column
ROW_IN = 0.26  # height per claim row of the forest plot


def png_bytes(fig) -> bytes:
    """`fig` as PNG bytes with a tight box (no label cut at the canvas edge), then closed."""
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return buffer.getvalue()


def status_table(frame: pd.DataFrame) -> pd.DataFrame:
    """Counts of the findings and readings by document (rows, in order of appearance) x status (columns,
    in the order of `STATUSES`, those with no claim left out)."""
    tallied = frame[frame["category"].isin(TALLIED)] if "category" in frame else frame
    documents = list(dict.fromkeys(tallied["document"]))
    counts = pd.crosstab(tallied["document"], tallied["status"]).reindex(documents)
    return counts[[s for s in STATUSES if s in counts.columns]]


def status_chart(frame: pd.DataFrame) -> bytes | None:
    """One horizontal bar per source document, stacked by status, each segment labelled with its count."""
    if "document" not in frame or frame.empty:
        return None
    counts = status_table(frame)
    if counts.empty:
        return None
    fig, ax = plt.subplots(figsize=(WIDTH_IN, 0.55 * len(counts) + 1.2))
    left = np.zeros(len(counts))
    for status in counts.columns:
        values = counts[status].to_numpy(dtype=float)
        ax.barh(counts.index, values, left=left, color=STATUS_FILL[status], edgecolor="#444", label=status)
        for y, (x0, n) in enumerate(zip(left, values, strict=True)):
            if n:
                ax.text(x0 + n / 2, y, f"{n:.0f}", ha="center", va="center", fontsize=10)
        left += values
    ax.invert_yaxis()  # the first document on top, as in the tables
    ax.set_xlabel("claims (findings and readings)")
    ax.set_title("Status of each source document's claims")
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False, title="status")
    ax.spines[["top", "right"]].set_visible(False)
    return png_bytes(fig)


def _finite(value) -> float:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return math.nan
    return number if math.isfinite(number) else math.nan


def forest_rows(frame: pd.DataFrame) -> pd.DataFrame:
    """The claims with an estimate and a two-sided interval, as floats, grouped by `scale` (factor first,
    then the metrics by name) and in ledger order within a scale."""
    needed = ("scale", "estimate", "low", "high")
    if frame.empty or any(c not in frame for c in needed):
        return pd.DataFrame(columns=["claim", "status", *needed, "reference", "tolerance"])
    rows = frame[frame["status"] != NOT_RUN].copy()
    for column in ("estimate", "low", "high", "reference", "tolerance"):
        rows[column] = rows.get(column, pd.Series(math.nan, index=rows.index)).map(_finite)
    rows = rows.dropna(subset=["estimate", "low", "high"])
    rows["order"] = range(len(rows))
    rows["scale_key"] = rows["scale"].map(lambda s: "" if s == "factor" else str(s))
    return rows.sort_values(["scale_key", "order"]).drop(columns=["order", "scale_key"])


def _panel(ax, part: pd.DataFrame, scale: str) -> None:
    log = scale == "factor"
    y = np.arange(len(part))
    null = 1.0 if log else 0.0
    ax.axvline(null, color="#888", lw=1, zorder=0)
    for i, (_, row) in enumerate(part.iterrows()):
        ink = STATUS_INK.get(row["status"], "#000000")
        tolerance = row["tolerance"]
        if math.isfinite(tolerance):  # a comparable (or not-worse) claim's band around no difference
            low, high = (1 / tolerance, tolerance) if log else (-tolerance, tolerance)
            ax.fill_betweenx([i - 0.4, i + 0.4], low, high, color="#dde7f3", zorder=0)
        ax.plot([row["low"], row["high"]], [i, i], color=ink, lw=2)
        ax.plot(row["estimate"], i, "o", color=ink, ms=6)
        if math.isfinite(row["reference"]):
            ax.plot(row["reference"], i, "D", mfc="white", mec="#000", ms=6)
    ax.set_yticks(y, part["claim"])
    ax.set_ylim(len(part) - 0.5, -0.5)
    if log:
        ax.set_xscale("log")
        ax.set_xlabel("effect as a factor (1 = no difference)")
    else:
        ax.set_xlabel(f"effect as a difference in {scale} (0 = no difference)")
    ax.grid(axis="x", color="#eee")
    ax.spines[["top", "right"]].set_visible(False)


def forest_plot(frame: pd.DataFrame) -> bytes | None:
    """Every claim's estimate and interval by scale (module docstring); None without any."""
    rows = forest_rows(frame)
    if rows.empty:
        return None
    scales = list(dict.fromkeys(rows["scale"]))
    heights = [max(len(rows[rows["scale"] == s]), 1) + 1.5 for s in scales]
    fig, axes = plt.subplots(
        len(scales), 1, figsize=(WIDTH_IN, ROW_IN * sum(heights) + 0.8), height_ratios=heights, squeeze=False
    )
    for ax, scale in zip(axes[:, 0], scales, strict=True):
        _panel(ax, rows[rows["scale"] == scale], scale)
    shown = [s for s in STATUSES if s in set(rows["status"])]
    handles = [Line2D([], [], color=STATUS_INK[s], marker="o", lw=2, label=s) for s in shown]
    handles.append(Line2D([], [], ls="", marker="D", mfc="white", mec="#000", label="published size"))
    handles.append(plt.Rectangle((0, 0), 1, 1, color="#dde7f3", label="tolerance (comparable)"))
    axes[0, 0].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), frameon=False)
    axes[0, 0].set_title(
        "Each claim's effect (dot) and its interval: a better / not-worse claim's arm a ahead, a comparable "
        "claim's a - b",
        loc="left",
        fontsize=10,
    )
    fig.tight_layout()
    return png_bytes(fig)
