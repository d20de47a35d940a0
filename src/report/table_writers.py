"""Writers of the report tables (`src/report/tables.py` builds them): Markdown, LaTeX (booktabs) and CSV,
with the best value of each column marked and the notes under the table. One cell text for every writer
(`cells`), so the three agree."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from pathlib import Path

import pandas as pd

from src.io.atomic import atomic_write_text
from src.report.tables import MISSING, NOISY_ROW, RUNS_COLUMN, metric_specs


def best_rows(table: pd.DataFrame) -> dict[str, set[int]]:
    """Per metric label, the row positions holding its best mean (all of them on a tie); the noisy input's
    row (`NOISY_ROW`) is never one."""
    out: dict[str, set[int]] = {}
    first = table.index.get_level_values(0).astype(str)
    method = pd.Series(first != NOISY_ROW)  # the noisy input is no method: never the best
    for label, (_, higher, _) in metric_specs(table).items():
        # Means are floats already; a NaN (no run of the row logged the metric) is never the best.
        values = pd.to_numeric(table[label], errors="coerce").reset_index(drop=True).where(method)
        if higher is None or values.dropna().nunique() < 2:  # one value, or all tied: nothing stands out
            continue
        target = values.max() if higher else values.min()
        out[label] = {i for i, v in values.items() if v == target}
    return out


def _fmt(value: float, fmt: str) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return MISSING
    return fmt.format(value)


def mean_std_text(mean: float, std: float, fmt: str) -> tuple[str, str]:
    """`mean ± std` as two texts without float noise: the std to two significant digits, in plain
    decimals (0.000073, never 7.259e-05), and the mean rounded to the std's last digit where its own
    format (`fmt`) shows more than the spread supports (0.08885 ± 0.001788 -> 0.0889 ± 0.0018). A std of
    0 (a deterministic method) and a mean in scientific notation keep `fmt`."""
    mean_text = _fmt(mean, fmt)
    if not std > 0 or not math.isfinite(std) or "e" in mean_text or mean_text == MISSING:
        return mean_text, _fmt(std, fmt)
    digits = 1 - math.floor(math.log10(std))  # decimals of two significant digits (negative: tens...)
    spec = f"{',' if ',' in mean_text else ''}.{max(digits, 0)}f"
    shown = len(mean_text.partition(".")[2])
    if digits < shown:
        mean_text = format(round(mean, digits), spec)
    return mean_text, format(round(std, digits), spec)


def cells(
    table: pd.DataFrame, best: Mapping[str, set[int]] | None = None
) -> tuple[list[str], list[bool | None], list[list[tuple[str, str | None, bool]]]]:
    """(header labels, per-column higher_is_better (None for axes/runs), rows of (mean text, std text or
    None, bold)) for the renderers."""
    metrics = metric_specs(table)
    best = best_rows(table) if best is None else best
    axes = list(table.index.names)
    header = [str(a) for a in axes] + list(metrics) + [RUNS_COLUMN]
    directions: list[bool | None] = [None] * len(axes) + [spec[1] for spec in metrics.values()] + [None]
    rows = []
    for i, (index, row) in enumerate(table.iterrows()):
        keys = index if isinstance(index, tuple) else (index,)
        line: list[tuple[str, str | None, bool]] = [(str(k), None, False) for k in keys]
        for label, (_, _, fmt) in metrics.items():
            std = row.get(f"{label} std", math.nan)  # a table without std columns shows means only
            if pd.isna(std) or row[RUNS_COLUMN] < 2:
                mean_text, std_text = _fmt(row[label], fmt), None
            else:
                mean_text, std_text = mean_std_text(row[label], float(std), fmt)
            line.append((mean_text, std_text, i in best.get(label, set())))
        line.append((str(int(row[RUNS_COLUMN])), None, False))
        rows.append(line)
    return header, directions, rows


def _arrow(higher: bool | None, up: str, down: str) -> str:
    return "" if higher is None else f" {up if higher else down}"


def _notes(notes: Iterable[str] | str | None) -> list[str]:
    if notes is None:
        return []
    return [notes] if isinstance(notes, str) else [str(n) for n in notes]


def to_markdown(table: pd.DataFrame, best: Mapping[str, set[int]] | None = None, notes=None) -> str:
    """GitHub Markdown table; best value per metric column in **bold**, `mean ± std` over several runs.
    `notes` (e.g. the differing-params warning) go above the table as block quotes."""
    header, directions, rows = cells(table, best)

    def esc(text: str) -> str:
        return text.replace("|", "\\|")

    heads = [esc(h) + _arrow(d, "↑", "↓") for h, d in zip(header, directions, strict=True)]
    align = ["---" if d is None and i < len(table.index.names) else "---:" for i, d in enumerate(directions)]
    lines = [f"> **Warning:** {esc(n)}\n" for n in _notes(notes)]
    lines += ["| " + " | ".join(heads) + " |", "|" + "|".join(align) + "|"]
    for row in rows:
        texts = []
        for mean, std, bold in row:
            text = esc(mean if std is None else f"{mean} ± {std}")
            texts.append(f"**{text}**" if bold else text)
        lines.append("| " + " | ".join(texts) + " |")
    return "\n".join(lines) + "\n"


_LATEX_SPECIAL = {
    "\\": r"\textbackslash{}",
    "&": r"\&",
    "%": r"\%",
    "$": r"\$",
    "#": r"\#",
    "_": r"\_",
    "{": r"\{",
    "}": r"\}",
    "~": r"\textasciitilde{}",
    "^": r"\textasciicircum{}",
}


def latex_escape(text: str) -> str:
    """Escape LaTeX's special characters (underscores in model names, `%`, ...)."""
    return "".join(_LATEX_SPECIAL.get(ch, ch) for ch in str(text))


def to_latex(table: pd.DataFrame, best: Mapping[str, set[int]] | None = None, notes=None) -> str:
    """booktabs `tabular` (\\toprule, \\midrule, \\bottomrule); best value per column in \\textbf{};
    `notes` as a full-width row under the table (and as `%` comments)."""
    header, directions, rows = cells(table, best)
    n_axes = len(table.index.names)
    spec = "l" * n_axes + "r" * (len(header) - n_axes)
    heads = [
        latex_escape(h) + _arrow(d, r"$\uparrow$", r"$\downarrow$")
        for h, d in zip(header, directions, strict=True)
    ]
    lines = [f"% Warning: {n}" for n in _notes(notes)]
    lines += [f"\\begin{{tabular}}{{{spec}}}", r"\toprule", " & ".join(heads) + r" \\", r"\midrule"]
    for row in rows:
        texts = []
        for mean, std, bold in row:
            text = latex_escape(mean) if std is None else f"{latex_escape(mean)} $\\pm$ {latex_escape(std)}"
            texts.append(f"\\textbf{{{text}}}" if bold else text)
        lines.append(" & ".join(texts) + r" \\")
    lines.append(r"\bottomrule")
    for note in _notes(notes):
        cell = f"\\footnotesize Warning: {latex_escape(note)}"
        lines.append(f"\\multicolumn{{{len(header)}}}{{p{{0.95\\linewidth}}}}{{{cell}}} \\\\")
    lines.append(r"\end{tabular}")
    return "\n".join(lines) + "\n"


def to_csv(table: pd.DataFrame, notes=None) -> str:
    """Plain numbers: axis columns, then per metric `<label>` (mean) and `<label> std`, then `runs`.
    `notes` become leading `# ` comment lines (read back with `pandas.read_csv(..., comment="#")`)."""
    text = table.reset_index().to_csv(index=False, float_format="%.10g")
    comments = "".join(f"# Warning: {n}\n" for n in _notes(notes))
    return comments + text


def write_table_with_notes(
    stem: str,
    table: pd.DataFrame,
    out_dir: Path,
    warnings: Iterable[str],
    notes: Iterable[str],
    best: Mapping[str, set[int]] | None = None,
) -> dict[str, Path]:
    """`<stem>.{md,tex,csv}` in `out_dir`: the table, the report's warnings above it, `notes` (what its
    numbers mean, not warnings) below it; `best` as `to_markdown`'s. Returns {file name: path}."""
    warnings, notes, out_dir = list(warnings), list(notes), Path(out_dir)
    markdown = to_markdown(table, best, notes=warnings) + "\n" + "".join(f"- {n}\n" for n in notes)
    latex = to_latex(table, best, notes=warnings) + "".join(f"% {n}\n" for n in notes)
    csv = "".join(f"# {n}\n" for n in notes) + to_csv(table, notes=warnings)
    return {
        f"{stem}.md": atomic_write_text(out_dir / f"{stem}.md", markdown),
        f"{stem}.tex": atomic_write_text(out_dir / f"{stem}.tex", latex),
        f"{stem}.csv": atomic_write_text(out_dir / f"{stem}.csv", csv),
    }
