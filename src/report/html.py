"""One self-contained HTML page: title, a smoke-profile banner, warnings, tables (best values bold, the
noisy input's row in italics, wide tables scrolling inside the page), extra sections (the filter search's
best expressions), figures embedded as base64 PNGs, and the runs it was built from (run ids, git
commits)."""

from __future__ import annotations

import base64
import html
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import pandas as pd

from src.report.table_writers import cells
from src.report.tables import MISSING, NOISY_ROW, RUNS_COLUMN, column_legend

_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; padding: 0 1em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.92em; }
.scroll { overflow-x: auto; max-width: 100%; } td.num { white-space: nowrap; }
tr.noisy td { font-style: italic; color: #555; }
.plain td, .plain th { text-align: left; }
.smoke { background: #f8d7da; border: 1px solid #d08080; padding: 0.6em 1em; margin: 1em 0; }
th, td { padding: 0.3em 0.8em; border-bottom: 1px solid #ddd; text-align: right; }
th { border-bottom: 2px solid #444; } td.key, th.key { text-align: left; }
.warning { background: #fff3cd; border: 1px solid #e0c060; padding: 0.6em 1em; margin: 1em 0; }
img { max-width: 100%; border: 1px solid #ccc; } code { font-size: 0.9em; }
.legend { font-size: 0.85em; color: #444; margin: -1.2em 0 1.5em; line-height: 1.35; }
"""


def table_html(table: pd.DataFrame) -> str:
    """`<table>` of a report table: `mean ± std` cells, the best value per metric column in bold."""
    header, directions, rows = cells(table)
    n_axes = len(table.index.names)
    heads = []
    for i, (head, higher) in enumerate(zip(header, directions, strict=True)):
        arrow = "" if higher is None else (" &uarr;" if higher else " &darr;")
        heads.append(f'<th class="{"key" if i < n_axes else "num"}">{html.escape(head)}{arrow}</th>')
    lines = ['<div class="scroll"><table>', "<thead><tr>" + "".join(heads) + "</tr></thead>", "<tbody>"]
    for row in rows:
        tds = []
        for i, (mean, std, bold) in enumerate(row):
            text = html.escape(mean if std is None else f"{mean} ± {std}")
            text = f"<b>{text}</b>" if bold else text
            tds.append(f'<td class="{"key" if i < n_axes else "num"}">{text}</td>')
        noisy = ' class="noisy"' if row[0][0] == NOISY_ROW else ""
        lines.append(f"<tr{noisy}>" + "".join(tds) + "</tr>")
    lines += ["</tbody>", "</table></div>"]
    return "\n".join(lines)


def legend_html(table: pd.DataFrame) -> str:
    """One line under the table for each column a reader could misread (`tables.column_legend`)."""
    lines = column_legend([*table.columns, RUNS_COLUMN])
    return f'<div class="legend">{"<br>".join(html.escape(line) for line in lines)}</div>' if lines else ""


def _img(path: Path, alt: str) -> str:
    data = base64.b64encode(Path(path).read_bytes()).decode("ascii")
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def _runs_html(runs: pd.DataFrame, labels: Sequence[str]) -> str:
    lines = [
        '<div class="scroll"><table>',
        '<thead><tr><th class="key">run</th><th class="key">run id</th><th class="key">name</th>'
        '<th class="key">seed</th><th class="key">git commit</th><th class="key">data</th></tr></thead>',
        "<tbody>",
    ]
    for label, (_, run) in zip(labels, runs.iterrows(), strict=True):
        values = [
            label,
            run.get("run_id"),
            run.get("tags.mlflow.runName"),
            run.get("params.seed"),
            run.get("tags.nrbench.git_commit"),
            run.get("tags.nrbench.data_fingerprint"),
        ]
        texts = [
            MISSING if v is None or (isinstance(v, float) and pd.isna(v)) else html.escape(str(v))
            for v in values
        ]
        lines.append("<tr>" + "".join(f'<td class="key"><code>{t}</code></td>' for t in texts) + "</tr>")
    lines += ["</tbody>", "</table></div>"]
    return "\n".join(lines)


def render_html(
    title: str,
    tables: Mapping[str, pd.DataFrame],
    figures: Mapping[str, Path | None],
    runs: pd.DataFrame,
    labels: Sequence[str],
    notes: Iterable[str] = (),
    subtitle: str = "",
    banner: str | None = None,
    links: str = "",
    sections: Mapping[str, str] | None = None,
) -> str:
    """The whole page; `tables` and `figures` map section headings to content (a None figure is left
    out). `banner` (the smoke-profile note) comes first, above the title; `links` (HTML: the site's
    index, the method pages) under the subtitle; `sections` (heading: HTML) after the tables."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{_STYLE}</style></head><body>",
    ]
    if banner:
        parts.append(f'<div class="smoke"><b>{html.escape(banner)}</b></div>')
    parts.append(f"<h1>{html.escape(title)}</h1>")
    if subtitle:
        parts.append(f"<p>{html.escape(subtitle)}</p>")
    if links:
        parts.append(f"<p>{links}</p>")
    for note in notes:
        parts.append(f'<div class="warning"><b>Warning:</b> {html.escape(note)}</div>')
    for heading, table in tables.items():
        parts += [f"<h2>{html.escape(heading)}</h2>", table_html(table), legend_html(table)]
    for heading, content in (sections or {}).items():
        parts += [f"<h2>{html.escape(heading)}</h2>", content]
    for heading, path in figures.items():
        if path is not None:
            parts += [f"<h2>{html.escape(heading)}</h2>", f"<figure>{_img(path, heading)}</figure>"]
    parts += [f"<h2>Runs ({len(runs)})</h2>", _runs_html(runs, labels), "</body></html>"]
    return "\n".join(parts) + "\n"
