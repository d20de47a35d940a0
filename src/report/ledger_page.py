"""The ledger's files: `ledger.md` (the headline count and one table per kind of claim), `ledger.html` (the
same, self-contained, statuses coloured), `ledger.csv` (every column, for scripts and the snapshot) and
`items/<claim>.csv` (the per-replicate differences behind each status). Written atomically: a crash
leaves the previous ledger, never half of a new one.

The headline counts the seeds' findings and readings only; the project's own targets and the set-up
checks get tables of their own and are never counted as what a seed found.
"""

from __future__ import annotations

import html
import math
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from src.io.atomic import atomic_write_text
from src.report.claims import CATEGORIES, TALLIED
from src.report.verdicts import STATUSES, effect_text

COLUMNS = (
    "claim",
    "category",
    "source",
    "quote",
    "statement",
    "caveat",
    "profile",
    "from",
    "status",
    "measured",
    "published",
    "unit",
    "seeds",
    "images",
    "replicates",
    "undefined",
    "p",
    "p_adjusted",
    "family",
    "budget",
    "run_budget",
    "seed_budget",
    "not_counted",
    "numbers",
    "runs",
    "measured_on",
    "run_ids",
    "items_csv",
    "commits",
    "data",
)
#: What the Markdown and HTML tables show (the CSV has every column).
SHOWN = (
    "claim",
    "status",
    "measured",
    "published",
    "unit",
    "seeds",
    "images",
    "undefined",
    "profile",
    "from",
)
#: What each claim's details list under the tables, in this order: our budget beside the seed's.
DETAILS = ("quote", "caveat", "numbers", "budget", "run_budget", "seed_budget", "not_counted", "measured_on")
_COLOURS = {
    "reproduced": "#d4edda",
    "direction only": "#fff3cd",
    "not reproduced": "#f8d7da",
    "not distinguishable": "#e2e3e5",
    "underpowered": "#e7f1ff",
    "confounded": "#f3d9fa",
    "not run": "#ffffff",
}
_TITLES = {
    "finding": "Findings the seeds state",
    "reading": "Readings: the harness's interpretation of a quoted sentence",
    "target": "Targets: the project's own goals, not the seeds' findings (not counted)",
    "setup": "Set-up checks (checked by the tests, not counted)",
}
_STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1400px; padding: 0 1.5em;
       color: #222; }
table { border-collapse: collapse; font-size: 0.88em; }
th, td { padding: 0.35em 0.6em; border-bottom: 1px solid #ddd; text-align: left; vertical-align: top; }
th { border-bottom: 2px solid #444; } code { font-size: 0.9em; }
.scroll { overflow-x: auto; max-width: 100%; }
details { margin: 0.2em 0; font-size: 0.85em; }
"""


def _interval(row) -> str:
    """The estimate and its interval, as the numbers print them (a factor for log claims)."""
    verdict, log = row.verdict, row.claim.log
    if not math.isfinite(verdict.estimate):
        return "-"
    low, high = effect_text(verdict.low, log, 3), effect_text(verdict.high, log, 3)
    return f"{effect_text(verdict.estimate, log, 3)} [{low}, {high}]"


def _published(claim) -> str:
    """What the seed (or the project) gives to compare with: the size, tolerance or published values."""
    rule = claim.rule
    if rule.kind == "agreement":
        values = ", ".join(f"{case.value:g}" for case in rule.published)
        return f"{values} (±{rule.tolerance:g}; {rule.tolerance_source})"
    if rule.kind == "comparable":
        return f"within ±{rule.tolerance:g} ({rule.tolerance_source})"
    if rule.kind == "not_worse":
        return f"not behind by more than {rule.tolerance:g} ({rule.tolerance_source})"
    if rule.size and (rule.size > 1 or not claim.log):
        return f"{rule.size:g}x" if claim.log else f"{rule.size:+g}"
    return "no size given"


def _quote(claim) -> str:
    if not claim.quote:
        return ""
    return f'"{claim.quote}"' + (f" ({claim.translation})" if claim.translation else "")


def _p(value: float) -> str:
    return f"{value:.2g}" if math.isfinite(value) else "-"


def ledger_frame(rows: Sequence) -> pd.DataFrame:
    """One row per claim (`src.report.ledger.LedgerRow`), the columns of `COLUMNS`."""
    records = []
    for r in rows:
        replicates = r.replicates
        records.append(
            {
                "claim": r.claim.id,
                "category": r.claim.category,
                "source": r.claim.citation,
                "quote": _quote(r.claim),
                "statement": r.claim.statement,
                "caveat": r.claim.caveat or "-",
                "profile": r.profile,
                "from": r.runs_from,
                "status": r.verdict.status,
                "measured": _interval(r),
                "published": _published(r.claim),
                "unit": replicates.unit if replicates is not None else "-",
                "seeds": replicates.seeds if replicates is not None else "-",
                "images": replicates.images if replicates is not None else "-",
                "replicates": r.verdict.items,
                "undefined": f"{replicates.undefined[0]} / {replicates.undefined[1]}" if replicates else "-",
                "p": _p(r.verdict.p_value),
                "p_adjusted": _p(r.p_adjusted),
                "family": r.family or "-",
                "budget": r.arm_budget or "-",
                "run_budget": r.run_budget or "-",
                "seed_budget": r.claim.seed_budget or "-",
                "not_counted": r.not_counted or "-",
                "numbers": r.verdict.numbers,
                "runs": r.runs,
                "measured_on": r.measured_on or "-",
                "run_ids": " ".join(r.run_ids) or "-",
                "items_csv": f"items/{r.claim.id}.csv" if replicates is not None else "-",
                "commits": " ".join(r.commits) or "-",
                "data": " ".join(r.fingerprints) or "-",
            }
        )
    return pd.DataFrame(records, columns=list(COLUMNS))


def status_counts(frame: pd.DataFrame) -> str:
    """ "3 reproduced, 1 direction only, ..." over the findings and readings (the headline), in the order
    of `STATUSES` (zero counts left out)."""
    tallied = frame[frame["category"].isin(TALLIED)] if "category" in frame else frame
    counts = tallied["status"].value_counts()
    return ", ".join(f"{counts[s]} {s}" for s in STATUSES if s in counts) or "no claims"


def _cell(value) -> str:
    return str(value).replace("|", "\\|").replace("\n", " ")


def ledger_markdown(frame: pd.DataFrame, subtitle: str) -> str:
    lines = ["# Reproduction ledger", "", subtitle, "", f"**{status_counts(frame)}** (findings and readings)"]
    for category in CATEGORIES:
        part = frame[frame["category"] == category]
        if part.empty:
            continue
        lines += [
            "",
            f"## {_TITLES[category]}",
            "",
            "| " + " | ".join(SHOWN) + " |",
            "|" + "---|" * len(SHOWN),
        ]
        lines += ["| " + " | ".join(_cell(row[c]) for c in SHOWN) + " |" for _, row in part.iterrows()]
    lines += ["", "## Each claim", ""]
    for _, row in frame.iterrows():
        lines.append(f"- **{row['claim']}** ({row['category']}, {row['source']}): {_cell(row['statement'])}")
        for key in (*DETAILS, "family", "items_csv"):
            if row[key] not in ("", "-"):
                lines.append(f"  - {key}: {_cell(row[key])}")
    return "\n".join(lines) + "\n"


def _html_table(part: pd.DataFrame) -> list[str]:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in SHOWN)
    body = []
    for _, row in part.iterrows():
        colour = _COLOURS.get(row["status"], "#ffffff")
        cells = []
        for c in SHOWN:
            text = html.escape(str(row[c]))
            if c == "status":
                cells.append(f'<td style="background:{colour}"><b>{text}</b></td>')
            elif c == "claim":
                details = "".join(
                    f"<div><i>{key}</i>: {html.escape(str(row[key]))}</div>"
                    for key in ("source", "statement", *DETAILS)
                    if str(row[key]) not in ("", "-")
                )
                link = row["items_csv"]
                if link != "-":
                    details += f'<div><a href="{html.escape(link)}">per-replicate differences</a></div>'
                cells.append(
                    f"<td><code>{text}</code><details><summary>details</summary>{details}</details></td>"
                )
            else:
                cells.append(f"<td>{text}</td>")
        body.append(f"<tr>{''.join(cells)}</tr>")
    return [
        f'<div class="scroll"><table><thead><tr>{head}</tr></thead><tbody>',
        *body,
        "</tbody></table></div>",
    ]


def ledger_html(frame: pd.DataFrame, subtitle: str) -> str:
    sections = []
    for category in CATEGORIES:
        part = frame[frame["category"] == category]
        if not part.empty:
            sections += [f"<h2>{html.escape(_TITLES[category])}</h2>", *_html_table(part)]
    return (
        "\n".join(
            [
                "<!DOCTYPE html>",
                '<html lang="en"><head><meta charset="utf-8">',
                f"<title>Reproduction ledger</title><style>{_STYLE}</style></head><body>",
                "<h1>Reproduction ledger</h1>",
                f"<p>{html.escape(subtitle)}</p>",
                f"<p><b>{html.escape(status_counts(frame))}</b> (findings and readings)</p>",
                '<p><a href="index.html">All reports</a></p>',
                *sections,
                "</body></html>",
            ]
        )
        + "\n"
    )


def _items_csv(row) -> str:
    """A claim's per-replicate differences (a - b; log ratios for log claims), one line per replicate."""
    d = row.replicates.difference
    frame = pd.DataFrame(
        {row.replicates.unit.removesuffix("s"): d.index.astype(str), "a_minus_b": d.to_numpy()}
    )
    return frame.to_csv(index=False)


def write_ledger(frame: pd.DataFrame, out_dir: Path, subtitle: str, rows: Sequence = ()) -> dict[str, Path]:
    """`ledger.{md,html,csv}` and `items/<claim>.csv` under `out_dir`, with `items/index.csv` listing the
    claims that have items (written even when none has: the folder is a DVC output of the ledger stage,
    and a store without a counted run, e.g. at `profile=smoke`, must not fail it); returns the ledger
    paths by suffix."""
    out_dir = Path(out_dir)
    listed = []
    for row in rows:
        if row.replicates is not None:
            atomic_write_text(out_dir / "items" / f"{row.claim.id}.csv", _items_csv(row))
            listed.append(
                {"claim": row.claim.id, "file": f"{row.claim.id}.csv", "replicates": row.verdict.items}
            )
    index = pd.DataFrame(listed, columns=["claim", "file", "replicates"])
    atomic_write_text(out_dir / "items" / "index.csv", index.to_csv(index=False))
    texts = {
        "md": ledger_markdown(frame, subtitle),
        "html": ledger_html(frame, subtitle),
        "csv": frame.to_csv(index=False),
    }
    return {suffix: atomic_write_text(out_dir / f"ledger.{suffix}", text) for suffix, text in texts.items()}
