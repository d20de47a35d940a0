"""The ledger's files: `ledger.md` (the headline count and one table per kind of claim), `ledger.html` (the
same, self-contained, statuses coloured), `ledger.csv` (every column, for scripts and the snapshot) and
`items/<claim>.csv` (the per-replicate differences behind each status). Written atomically: a crash
leaves the previous ledger, never half of a new one.

The headline counts the seeds' findings and readings only; the project's own targets and the set-up
checks get tables of their own and are never counted as what a seed found.
"""

from __future__ import annotations

import base64
import html
import math
from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from src.io.atomic import atomic_write_text
from src.report.claims import CATEGORIES, TALLIED
from src.report.ledger_figures import STATUS_FILL, forest_plot, status_chart
from src.report.shown_ledger import choose
from src.report.verdicts import NOT_RUN, STATUSES, effect_text

COLUMNS = (
    "claim",
    "category",
    "document",
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
    "to_run",
    "scale",
    "estimate",
    "low",
    "high",
    "reference",
    "tolerance",
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
DETAILS = (
    "quote",
    "caveat",
    "numbers",
    "budget",
    "run_budget",
    "seed_budget",
    "not_counted",
    "measured_on",
    "to_run",
)
#: The HTML tables' columns (grouped by source document: the document is the section; the category marks
#: a target or set-up check among the findings); the site's index shows `SHOWN_ON_INDEX`.
SHOWN_BY_DOCUMENT = ("claim", "category", *SHOWN[1:])
SHOWN_ON_INDEX = ("claim", "status", "measured", "published", "unit", "profile", "from")
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
.origin { background: #eef4fb; border: 1px solid #b5c9e0; padding: 0.5em 0.8em; }
.legend { font-size: 0.85em; color: #444; } .nowrap { white-space: nowrap; }
img { max-width: 100%; }
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


def effect_numbers(row) -> dict[str, float | str]:
    """The estimate and interval as numbers on the scale the ledger prints them (`scale`: "factor" for a
    log claim, exp of the log ratio, else the metric's name for a difference), with the published size
    (`reference`) and the comparable / not-worse tolerance on that scale (NaN where the rule has none):
    what the forest plot draws."""
    claim, verdict = row.claim, row.verdict
    rule = claim.rule
    on_scale = math.exp if claim.log else float
    size = rule.size if rule.kind == "better" and rule.size and (rule.size > 1 or not claim.log) else math.nan
    tolerance = rule.tolerance if rule.kind in ("comparable", "not_worse") else math.nan
    return {
        "scale": "factor" if claim.log else claim.metric,
        "estimate": on_scale(verdict.estimate),
        "low": on_scale(verdict.low),
        "high": on_scale(verdict.high),
        # a log claim's size is already a factor (`10` for "10x"); its tolerance is a natural-log width
        "reference": size,
        "tolerance": on_scale(tolerance),
    }


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
                "document": r.claim.document,
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
                "to_run": r.routes or "-",
                **effect_numbers(r),
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


#: What each column of the ledger's tables means, under each table (one line each).
LEGEND = (
    "measured: the Hodges-Lehmann estimate of arm a's advantage with its interval (a factor for a log "
    "claim, else a difference in the metric's units); published: the size or tolerance the claim is "
    "judged against; unit: what replicates (training seeds, or images for a deterministic method); "
    "undefined: replicates with an undefined output / all; from: the study, pipeline or benchmark whose "
    "runs were counted."
)


def _claim_cell(row: pd.Series, items_href=None) -> str:
    """The claim's id with its details folded (source, statement, quote, numbers, budgets, routes) and the
    link to its per-replicate differences (`items_href(items_csv)`, None: no link)."""
    details = "".join(
        f"<div><i>{key}</i>: {html.escape(str(row[key]))}</div>"
        for key in ("source", "statement", *DETAILS)
        if key in row and str(row[key]) not in ("", "-", "nan")
    )
    link = row.get("items_csv", "-")
    href = items_href(str(link)) if items_href and link not in ("-", "", None) else None
    if href:
        details += f'<div><a href="{html.escape(href)}">per-replicate differences</a></div>'
    claim = html.escape(str(row["claim"]))
    return f"<td><code>{claim}</code><details><summary>details</summary>{details}</details></td>"


def status_cell(status: str) -> str:
    """A status as a coloured, bold table cell."""
    colour = STATUS_FILL.get(status, "#ffffff")
    return f'<td style="background:{colour}"><b>{html.escape(status)}</b></td>'


def _from_cell(source: str, study_href) -> str:
    href = study_href(source) if study_href else None
    text = html.escape(source)
    return f'<td><a href="{html.escape(href)}">{text}</a></td>' if href else f"<td>{text}</td>"


def _ran_table(part: pd.DataFrame, columns, study_href=None, items_href=None) -> list[str]:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in columns)
    body = []
    for _, row in part.iterrows():
        cells = []
        for c in columns:
            value = str(row.get(c, "-"))
            if c == "claim":
                cells.append(_claim_cell(row, items_href))
            elif c == "status":
                cells.append(status_cell(value))
            elif c == "from":
                cells.append(_from_cell(value, study_href))
            elif c == "measured":
                cells.append(f'<td class="nowrap">{html.escape(value)}</td>')
            else:
                cells.append(f"<td>{html.escape(value)}</td>")
        body.append(f"<tr>{''.join(cells)}</tr>")
    return [
        f'<div class="scroll"><table><thead><tr>{head}</tr></thead><tbody>',
        *body,
        "</tbody></table></div>",
    ]


def _not_run_list(part: pd.DataFrame) -> list[str]:
    """The claims not run, folded: each with its reason and its route at each profile, cheapest first."""
    items = []
    for _, row in part.iterrows():
        claim, category = html.escape(str(row["claim"])), html.escape(str(row.get("category", "-")))
        statement, reason = (
            html.escape(str(row.get("statement", ""))),
            html.escape(str(row.get("numbers", "-"))),
        )
        items.append(f"<li><code>{claim}</code> ({category}): {statement}<br><i>{reason}</i></li>")
    return [
        f"<details><summary>{len(part)} claim{'s' if len(part) != 1 else ''} not run: why, and the command "
        "at each profile (cheapest first)</summary><ul>",
        *items,
        "</ul></details>",
    ]


def document_sections(
    frame: pd.DataFrame,
    study_href=None,
    items_href=None,
    columns: Sequence[str] = SHOWN_BY_DOCUMENT,
    heading: str = "h2",
) -> list[str]:
    """Per source document: a heading, its claims that ran (status coloured, details folded; targets and
    set-up checks marked by their category, never counted in the headline) and its claims not run, folded.
    A document whose claims all did not run gets no table, only the folded list: never an empty table.
    `study_href(source)`: the link of a "from" cell, `items_href(items_csv)` of a claim's per-replicate
    differences (`ShownLedger.items_href`), each None for no link; `heading` the documents' heading tag."""
    sections: list[str] = []
    if frame.empty:
        return sections
    documents = frame["document"] if "document" in frame else pd.Series("claims", index=frame.index)
    for document in dict.fromkeys(documents):
        part = frame[documents == document]
        ran, not_run = part[part["status"] != NOT_RUN], part[part["status"] == NOT_RUN]
        order = {c: i for i, c in enumerate(CATEGORIES)}
        ran = ran.iloc[sorted(range(len(ran)), key=lambda i: order.get(ran["category"].iloc[i], len(order)))]
        counts = status_counts(part)
        sections.append(f"<{heading}>{html.escape(str(document))}</{heading}>")
        sections.append(f"<p>{html.escape(counts)} (findings and readings)</p>")
        if len(ran):
            sections += _ran_table(ran, columns, study_href, items_href)
        if len(not_run):
            sections += _not_run_list(not_run)
    if sections:
        sections.append(f'<p class="legend">{html.escape(LEGEND)}</p>')
    return sections


def figure_img(png: bytes | None, alt: str) -> list[str]:
    """An embedded PNG (`<img>` with a base64 data URI), or nothing."""
    if png is None:
        return []
    data = base64.b64encode(png).decode("ascii")
    return [f'<figure><img alt="{html.escape(alt)}" src="data:image/png;base64,{data}"></figure>']


def ledger_figures(frame: pd.DataFrame) -> list[str]:
    """The status chart and the forest plot (`src.report.ledger_figures`), each with its heading."""
    parts = []
    chart = status_chart(frame)
    if chart is not None:
        parts += ["<h2>Status by source document</h2>", *figure_img(chart, "claims by document and status")]
    forest = forest_plot(frame)
    if forest is not None:
        parts += [
            "<h2>Effects and intervals</h2>",
            *figure_img(forest, "each claim's effect and interval"),
            '<p class="legend">Each row is a claim that ran: its estimate (dot) and interval (line), '
            "coloured by status; the diamond is the published size where the source gives one; the shaded "
            "band a comparable claim's tolerance. Agreement claims (published values) have no single "
            "interval and are not drawn.</p>",
        ]
    return parts


def ledger_html(frame: pd.DataFrame, subtitle: str, label: str = "", items_href=None) -> str:
    """The whole ledger page: where it comes from (`label`), the methods (`subtitle`), the headline, the
    figures and one section per source document."""
    return (
        "\n".join(
            [
                "<!DOCTYPE html>",
                '<html lang="en"><head><meta charset="utf-8">',
                f"<title>Reproduction ledger</title><style>{_STYLE}</style></head><body>",
                "<h1>Reproduction ledger</h1>",
                f'<p class="origin">{html.escape(label)}</p>' if label else "",
                f"<p>{html.escape(subtitle)}</p>" if subtitle else "",
                f"<p><b>{html.escape(status_counts(frame))}</b> (findings and readings)</p>"
                if len(frame)
                else "<p>No ledger yet: <code>python -m src.run stage=ledger</code> writes one.</p>",
                '<p><a href="index.html">All reports</a></p>',
                *ledger_figures(frame),
                *document_sections(frame, items_href=items_href),
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
    """`ledger.{md,csv}` and `items/<claim>.csv` under `out_dir`, with `items/index.csv` listing the
    claims that have items (written even when none has: the folder is a DVC output of the ledger stage,
    and a store without a counted run, e.g. at `profile=smoke`, must not fail it); returns the ledger
    paths by suffix. The HTML page is `write_ledger_page`'s: it may show the committed snapshot instead."""
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
    texts = {"md": ledger_markdown(frame, subtitle), "csv": frame.to_csv(index=False)}
    return {suffix: atomic_write_text(out_dir / f"ledger.{suffix}", text) for suffix, text in texts.items()}


def write_ledger_page(out_dir: Path, committed: Path | None) -> Path:
    """`<out_dir>/ledger.html`: the ledger `shown_ledger.choose` picks (this store's once it has a status,
    else the committed snapshot), labelled with where it comes from."""
    out_dir = Path(out_dir)
    shown = choose(out_dir / "ledger.csv", committed)
    page = ledger_html(shown.frame, shown.subtitle, shown.label, shown.items_href(out_dir))
    return atomic_write_text(out_dir / "ledger.html", page)
