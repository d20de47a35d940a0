"""The ledger's files: `ledger.md` (a status count and one table row per claim), `ledger.html` (the same,
self-contained, statuses coloured) and `ledger.csv` (for scripts). Written atomically: a crash leaves the
previous ledger, never half of a new one."""

from __future__ import annotations

import html
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from src.io.atomic import atomic_write_text
from src.report.verdicts import STATUSES

COLUMNS = ("claim", "source", "statement", "profile", "from", "status", "numbers", "runs", "commits", "data")
_COLOURS = {
    "reproduced": "#d4edda",
    "direction only": "#fff3cd",
    "not reproduced": "#f8d7da",
    "not distinguishable": "#e2e3e5",
    "not run": "#ffffff",
}
_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1400px; color: #222; }
table { border-collapse: collapse; font-size: 0.88em; }
th, td { padding: 0.35em 0.6em; border-bottom: 1px solid #ddd; text-align: left; vertical-align: top; }
th { border-bottom: 2px solid #444; } code { font-size: 0.9em; }
.scroll { overflow-x: auto; max-width: 100%; }
"""


def ledger_frame(rows: Sequence) -> pd.DataFrame:
    """One row per claim (`src.report.ledger.LedgerRow`), the columns of `COLUMNS`."""
    return pd.DataFrame(
        [
            {
                "claim": r.claim.id,
                "source": r.claim.citation,
                "statement": r.claim.statement,
                "profile": r.profile,
                "from": r.runs_from,
                "status": r.verdict.status,
                "numbers": r.verdict.numbers,
                "runs": r.runs,
                "commits": " ".join(r.commits) or "-",
                "data": " ".join(r.fingerprints) or "-",
            }
            for r in rows
        ],
        columns=list(COLUMNS),
    )


def status_counts(frame: pd.DataFrame) -> str:
    """ "3 reproduced, 1 direction only, ..." in the order of `STATUSES` (zero counts left out)."""
    counts = frame["status"].value_counts()
    return ", ".join(f"{counts[s]} {s}" for s in STATUSES if s in counts) or "no claims"


def ledger_markdown(frame: pd.DataFrame, subtitle: str) -> str:
    def cell(value) -> str:
        return str(value).replace("|", "\\|").replace("\n", " ")

    lines = ["# Reproduction ledger", "", subtitle, "", f"**{status_counts(frame)}**", ""]
    lines.append("| " + " | ".join(COLUMNS) + " |")
    lines.append("|" + "---|" * len(COLUMNS))
    lines += ["| " + " | ".join(cell(row[c]) for c in COLUMNS) + " |" for _, row in frame.iterrows()]
    return "\n".join(lines) + "\n"


def ledger_html(frame: pd.DataFrame, subtitle: str) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in COLUMNS)
    body = []
    for _, row in frame.iterrows():
        colour = _COLOURS.get(row["status"], "#ffffff")
        tds = "".join(
            f'<td style="background:{colour}"><b>{html.escape(str(row[c]))}</b></td>'
            if c == "status"
            else f"<td>{html.escape(str(row[c]))}</td>"
            for c in COLUMNS
        )
        body.append(f"<tr>{tds}</tr>")
    return (
        "\n".join(
            [
                "<!DOCTYPE html>",
                '<html lang="en"><head><meta charset="utf-8">',
                f"<title>Reproduction ledger</title><style>{_STYLE}</style></head><body>",
                "<h1>Reproduction ledger</h1>",
                f"<p>{html.escape(subtitle)}</p>",
                f"<p><b>{html.escape(status_counts(frame))}</b></p>",
                '<p><a href="index.html">All reports</a></p>',
                f'<div class="scroll"><table><thead><tr>{head}</tr></thead><tbody>',
                *body,
                "</tbody></table></div></body></html>",
            ]
        )
        + "\n"
    )


def write_ledger(frame: pd.DataFrame, out_dir: Path, subtitle: str) -> dict[str, Path]:
    """`ledger.{md,html,csv}` under `out_dir`; returns their paths by suffix."""
    out_dir = Path(out_dir)
    texts = {
        "md": ledger_markdown(frame, subtitle),
        "html": ledger_html(frame, subtitle),
        "csv": frame.to_csv(index=False),
    }
    return {suffix: atomic_write_text(out_dir / f"ledger.{suffix}", text) for suffix, text in texts.items()}
