"""The report site: `<report.out_dir>/index.html` linking every report, the ledger and the benchmark runs,
one page per compared method (`methods/<model>.html`) and one for the benchmark runs (`bench/index.html`).

Nothing in it is typed by hand: each entry comes from what exists under the reports folder, i.e. from the
logged runs through the pages built from them. A report (`src.report.build`) leaves `report.json` beside
its `index.html`: its title, experiments, profiles, run count, date, tables and, per method (`model.name`),
its configurations (the `model.*` params of its runs), parameter count and times. A folder with an
`index.html` and no `report.json` (a report built before it existed) is listed by its page's title and
file date. The ledger's findings (`ledger.csv`) head the index; the benchmark page reads the MLflow
experiment `nrbench-bench` (`python -m src.bench ... --log`). `build_site` runs after every report and
ledger is written, and writes every page atomically.
"""

from __future__ import annotations

import html
import json
import logging
import math
import os
import re
import tempfile
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import mlflow
import pandas as pd

from src.io.atomic import atomic_write_text
from src.report.collect import store_name
from src.report.table_writers import mean_std_text
from src.report.tables import NOISY_ROW

log = logging.getLogger("nrbench.report")

MANIFEST = "report.json"
METHODS_DIR = "methods"
BENCH_DIR = "bench"
#: The experiment `python -m src.bench ... --log` writes to (src/bench/bench_log.py::EXPERIMENT; the
#: report layer may not import the benchmarks, tests/test_site.py checks the two agree).
BENCH_EXPERIMENT = "nrbench-bench"
#: The profile whose numbers mean nothing (conf/profile/smoke.yaml: tiny data and budgets).
SMOKE = "smoke"
SMOKE_NOTE = (
    "Smoke profile: smoke runs check the plumbing (every stage runs end to end on tiny data with a tiny "
    "budget); their numbers mean nothing. Compare methods on cpu or paper runs."
)
#: Index sections, in order, by the MLflow experiment a report reads (studies: `report.name` sweeps/...).
CATEGORIES = {
    "nrbench-denoise": "Still-image denoisers",
    "nrbench-denoise-volumetric": "Volumetric sequences",
    "nrbench-filter_search": "Filter search",
    "nrbench-nerf": "Radiance fields",
}
STUDIES = "Studies (sweeps)"
OTHER = "Other reports"
#: Method page file names: a model name with other characters replaced by "_".
_UNSAFE = re.compile(r"[^\w.-]")

STYLE = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1200px; padding: 0 1em; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.92em; }
th, td { padding: 0.3em 0.8em; border-bottom: 1px solid #ddd; text-align: left; vertical-align: top; }
th { border-bottom: 2px solid #444; } td.num { text-align: right; }
.scroll { overflow-x: auto; max-width: 100%; }
.smoke { background: #f8d7da; border: 1px solid #d08080; padding: 0.6em 1em; margin: 1em 0; }
tr.noisy td { font-style: italic; color: #555; }
code, pre { font-size: 0.88em; } pre { background: #f6f6f6; padding: 0.6em; overflow-x: auto; }
img { max-width: 100%; } figure { margin: 0.5em 0; }
.origin { background: #eef4fb; border: 1px solid #b5c9e0; padding: 0.5em 0.8em; }
.legend { font-size: 0.85em; color: #444; } .nowrap { white-space: nowrap; }
details { margin: 0.2em 0; }
"""


def method_file(model: str) -> str:
    """`methods/<model>.html` (relative to the reports folder)."""
    return f"{METHODS_DIR}/{_UNSAFE.sub('_', str(model))}.html"


def relative(target: str, from_dir: str) -> str:
    """The link from a page in `from_dir` (relative to the reports folder, "" for its top) to `target`."""
    return Path(os.path.relpath(target, from_dir or ".")).as_posix()


def page(title: str, body: Iterable[str], banner: str | None = None) -> str:
    """A whole self-contained HTML page."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
    ]
    if banner:
        parts.append(f'<div class="smoke"><b>{html.escape(banner)}</b></div>')
    parts += [f"<h1>{html.escape(title)}</h1>", *body, "</body></html>"]
    return "\n".join(parts) + "\n"


def html_table(header: list[str], rows: Iterable[list[str]], classes: Iterable[str] | None = None) -> str:
    """A plain table of already-escaped cell HTML, inside a horizontally scrolling box."""
    classes = list(classes) if classes is not None else None
    lines = ['<div class="scroll"><table>', "<thead><tr>" + "".join(f"<th>{h}</th>" for h in header)]
    lines.append("</tr></thead><tbody>")
    for i, row in enumerate(rows):
        cls = f' class="{classes[i]}"' if classes and classes[i] else ""
        lines.append(f"<tr{cls}>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>")
    lines.append("</tbody></table></div>")
    return "\n".join(lines)


def _link(href: str, text: str) -> str:
    return f'<a href="{html.escape(href)}">{html.escape(text)}</a>'


def _number(value: Any, fmt: str = "{:.4g}") -> str:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return html.escape(str(value)) if value is not None and str(value) != "nan" else "-"
    return "-" if math.isnan(number) else html.escape(fmt.format(number))


# ------------------------------------------------------------------------------------------- scan


@dataclass
class Entry:
    """One report folder under the reports folder."""

    path: str  # its folder, relative to the reports folder ("denoise", "sweeps/temporal_loss")
    title: str
    category: str
    profiles: list[str] = field(default_factory=list)
    runs: int | None = None
    date: str = "-"
    manifest: dict[str, Any] = field(default_factory=dict)

    @property
    def smoke(self) -> bool:
        return SMOKE in self.profiles


def category(name: str, experiments: Iterable[str]) -> str:
    """The index section of a report: studies by folder, the others by the experiment they read."""
    if name.startswith("sweeps/"):
        return STUDIES
    for experiment in experiments:
        if experiment in CATEGORIES:
            return CATEGORIES[experiment]
    return OTHER


_TITLE = re.compile(r"<title>(.*?)</title>", re.S)


def scan(out_dir: Path) -> list[Entry]:
    """Every report folder under `out_dir` (one with an `index.html`, the site's own folders excepted),
    sorted by section and name."""
    entries = []
    for index in sorted(out_dir.rglob("index.html")):
        folder = index.parent.relative_to(out_dir).as_posix()
        if folder == "." or folder.split("/")[0] in (METHODS_DIR, BENCH_DIR):
            continue
        manifest_path = index.parent / MANIFEST
        if manifest_path.is_file():
            m = json.loads(manifest_path.read_text())
            entries.append(
                Entry(
                    folder,
                    str(m.get("title", folder)),
                    category(folder, m.get("experiments", [])),
                    list(m.get("profiles", [])),
                    m.get("runs"),
                    str(m.get("generated", "-")),
                    m,
                )
            )
        else:  # a report from before report.json: its page's title and its file's date
            match = _TITLE.search(index.read_text(errors="replace")[:4000])
            stamp = datetime.fromtimestamp(index.stat().st_mtime, UTC).strftime("%Y-%m-%d %H:%M UTC")
            title = html.unescape(match.group(1)) if match else folder
            legacy = {"denoise": "nrbench-denoise", "volumetric": "nrbench-denoise-volumetric"}
            experiments = [legacy.get(folder, f"nrbench-{folder}")]
            entries.append(Entry(folder, title, category(folder, experiments), date=stamp))
    order = [*CATEGORIES.values(), STUDIES, OTHER]
    return sorted(entries, key=lambda e: (order.index(e.category), e.path))


def methods(entries: Iterable[Entry]) -> dict[str, list[tuple[Entry, dict[str, Any]]]]:
    """{model: [(report entry, the report's record of the model)]} over the reports with a manifest."""
    out: dict[str, list[tuple[Entry, dict[str, Any]]]] = {}
    for entry in entries:
        for model, record in entry.manifest.get("methods", {}).items():
            out.setdefault(model, []).append((entry, record))
    return dict(sorted(out.items()))


# ------------------------------------------------------------------------------------------- bench


def bench_runs() -> pd.DataFrame:
    """The FINISHED runs of `BENCH_EXPERIMENT` in the current MLflow store, newest first (empty when the
    experiment does not exist or the store cannot be read)."""
    try:
        experiment = mlflow.tracking.MlflowClient().get_experiment_by_name(BENCH_EXPERIMENT)
        if experiment is None:
            return pd.DataFrame()
        runs = mlflow.search_runs(
            experiment_ids=[experiment.experiment_id],
            filter_string="attributes.status = 'FINISHED'",
            output_format="pandas",
        )
    except Exception as err:  # an unreachable store: the site is built without the benchmark
        log.warning("site: cannot read experiment %s (%s)", BENCH_EXPERIMENT, err)
        return pd.DataFrame()
    return runs.sort_values("start_time", ascending=False).reset_index(drop=True) if len(runs) else runs


def _seconds_columns(runs: pd.DataFrame) -> list[str]:
    return sorted(c for c in runs.columns if c.startswith("metrics.seconds_") and runs[c].notna().any())


def _date(value: Any) -> str:
    try:
        return pd.Timestamp(value).tz_convert("UTC").strftime("%Y-%m-%d %H:%M UTC")
    except (TypeError, ValueError):
        return "-"


def bench_page(runs: pd.DataFrame) -> str:
    """`bench/index.html`: per benchmark run its bench, profile, device, commit, date and each timed row's
    median ms per frame, then each run's printed report (`bench/report.txt`)."""
    if runs.empty:
        command = "<code>python -m src.bench denoise --log</code>"
        return page("Benchmark runs", [f"<p>No benchmark run in this store yet: {command} adds one.</p>"])
    seconds = _seconds_columns(runs)
    header = [
        "date",
        "bench",
        "profile",
        "device",
        "git commit",
        *(c.removeprefix("metrics.") for c in seconds),
    ]
    rows = []
    for _, run in runs.iterrows():
        rows.append(
            [
                _date(run.get("start_time")),
                html.escape(str(run.get("params.bench", "-"))),
                html.escape(str(run.get("tags.nrbench.profile", "-"))),
                html.escape(str(run.get("tags.nrbench.device", "-"))),
                f"<code>{html.escape(str(run.get('tags.nrbench.git_commit', '-')))}</code>",
                *(_number(run.get(c), "{:.6g}") for c in seconds),
            ]
        )
    body = [
        f"<p>{len(runs)} FINISHED runs of MLflow experiment <code>{BENCH_EXPERIMENT}</code> in "
        f"<code>{html.escape(store_name(mlflow.get_tracking_uri()))}</code>, newest first; "
        "<code>seconds_&lt;row&gt;</code> is each timed row's median seconds per frame over the rounds. "
        f'<a href="../index.html">All reports</a>.</p>',
        html_table(header, rows),
    ]
    with tempfile.TemporaryDirectory(prefix="nrbench-site-") as tmp:
        for i, (_, run) in enumerate(runs.iterrows()):
            try:
                local = mlflow.artifacts.download_artifacts(
                    run_id=run["run_id"], artifact_path="bench/report.txt", dst_path=f"{tmp}/{i}"
                )
                text = Path(local).read_text(errors="replace")
            except Exception as err:  # an older bench run without the artifact
                log.info("site: bench run %s has no bench/report.txt (%s)", run["run_id"], err)
                continue
            body.append(
                f"<h2>{html.escape(str(run.get('params.bench', '-')))} {_date(run.get('start_time'))}</h2>"
            )
            body.append(f"<pre>{html.escape(text)}</pre>")
    return page("Benchmark runs", body)


def bench_numbers(runs: pd.DataFrame, model: str) -> list[tuple[str, str, float]]:
    """(bench, date, seconds per frame) of every benchmark run that timed `model` (row key `model` or
    `<model>_net_only`)."""
    out = []
    for key in (model, f"{model}_net_only"):
        column = f"metrics.seconds_{key}"
        if column not in runs:
            continue
        for _, run in runs[runs[column].notna()].iterrows():
            label = f"{run.get('params.bench', '-')} ({key})"
            out.append((label, _date(run.get("start_time")), float(run[column])))
    return out


# ------------------------------------------------------------------------------------------- pages


def _table_rows(report_dir: Path, stem: str, model: str) -> pd.DataFrame | None:
    """The rows of table `<stem>.csv` whose `model` column is `model` or the noisy input (for scale)."""
    path = report_dir / f"{stem}.csv"
    if not path.is_file():
        return None
    table = pd.read_csv(path, comment="#", dtype={"model": str})
    if "model" not in table:
        return None
    rows = table[table["model"].isin([model, NOISY_ROW])]
    return rows if (rows["model"] == model).any() else None


def _value_format(number: float) -> str:
    """A whole number >= 1000 with thousands separators, other numbers to 4 significant digits."""
    return "{:,.0f}" if abs(number) >= 1000 and number == int(number) else "{:.4g}"


def _value(value: Any) -> str:
    """A table cell: a number in `_value_format`, text as it is, "-" for none."""
    try:
        number = float(value)
    except (TypeError, ValueError):
        return html.escape(str(value))
    if math.isnan(number):
        return "-"
    return _value_format(number).format(number)


def _mean_std_cells(table: pd.DataFrame) -> tuple[list[str], list[list[str]]]:
    """(header, rows) of a report table's CSV rows, each `<label>` with its `<label> std` as `mean ± std`
    (as on the report page)."""
    columns = [c for c in table.columns if not (c.endswith(" std") and c.removesuffix(" std") in table)]
    rows = []
    for _, row in table.iterrows():
        cells = []
        for c in columns:
            text = _value(row[c])
            std = pd.to_numeric(row.get(f"{c} std"), errors="coerce")
            if not pd.isna(std) and text != "-":  # as the report's cells: no float noise (mean_std_text)
                mean = float(row[c])
                text = " ± ".join(
                    html.escape(t) for t in mean_std_text(mean, float(std), _value_format(mean))
                )
            cells.append(text)
        rows.append(cells)
    return [html.escape(str(c)) for c in columns], rows


def method_page(model: str, records: list[tuple[Entry, dict[str, Any]]], out_dir: Path, bench) -> str:
    """`methods/<model>.html`: the model's configurations, parameter count, times, benchmark numbers and
    its row of every table of every report it appears in, each linking back to its report."""
    here = METHODS_DIR
    body = [f'<p><a href="{relative("index.html", here)}">All reports</a></p>', "<h2>Reports</h2>"]
    rows = []
    for entry, record in records:
        rows.append(
            [
                _link(relative(f"{entry.path}/index.html", here), entry.title),
                html.escape(", ".join(entry.profiles) or "-"),
                _number(record.get("runs"), "{:.0f}"),
                _number(record.get("param_count"), "{:,.0f}"),
                _number(record.get("train_time_s"), "{:.1f}"),
                _number(record.get("eval_ms_per_image"), "{:.1f}"),
                _number(record.get("eval_ms_per_mpixel"), "{:.1f}"),
                _number(record.get("eval_spp_equivalent"), "{:.1f}"),
                _number(record.get("eval_speedup"), "{:.2f}"),
            ]
        )
    header = ["report", "profile(s)", "runs", "params", "train time (s)", "ms / image", "ms / MP"]
    header += ["spp-equivalent", "speed-up"]
    body.append(html_table(header, rows))
    body.append(
        "<p>Times: means over the report's runs of the method (train time: the whole training). "
        "spp-equivalent and speed-up: each run's geometric mean over its held-out images and input counts "
        "(the samples a plain render needs for its error; the render time saved), averaged over the runs; "
        "per count in the report's Samples saved table.</p>"
    )
    marks = bench_numbers(bench, model) if len(bench) else []
    if marks:
        body.append("<h2>Benchmark</h2>")
        rows = [[html.escape(b), d, _number(s * 1000, "{:.2f}")] for b, d, s in marks]
        body.append(html_table(["bench (row)", "date", "ms / frame (median)"], rows))
        body.append(f'<p><a href="{relative(f"{BENCH_DIR}/index.html", here)}">All benchmark runs</a></p>')
    body.append("<h2>Configuration</h2>")
    seen: dict[str, list[str]] = {}
    configs: dict[str, dict[str, str]] = {}
    for entry, record in records:
        for config in record.get("configs", []):
            key = json.dumps(config["params"], sort_keys=True)
            configs[key] = config["params"]
            seen.setdefault(key, []).append(f"{entry.title} ({config.get('runs', '?')} runs)")
    for i, (key, params) in enumerate(configs.items()):
        body.append(f"<h3>Configuration {i + 1}: {html.escape('; '.join(seen[key]))}</h3>")
        rows = [
            [f"<code>{html.escape(k)}</code>", f"<code>{html.escape(str(v))}</code>"]
            for k, v in params.items()
        ]
        body.append(html_table(["config key", "value"], rows))
    body.append("<h2>Table rows</h2>")
    for entry, _ in records:
        for stem, heading in entry.manifest.get("tables", {}).items():
            table = _table_rows(out_dir / entry.path, stem, model)
            if table is None:
                continue
            link = _link(relative(f"{entry.path}/index.html", here), entry.title)
            body.append(f"<h3>{link}: {html.escape(heading)}</h3>")
            header, cells = _mean_std_cells(table)
            classes = ["noisy" if m == NOISY_ROW else "" for m in table["model"]]
            body.append(html_table(header, cells, classes))
    smoke = any(entry.smoke for entry, _ in records)
    return page(f"Method: {model}", body, banner=SMOKE_NOTE if smoke else None)


def _ledger_section(out_dir: Path, committed: Path | None) -> list[str]:
    """The ledger first (`shown_ledger.choose`: this store's once it has a status, else the committed
    snapshot), labelled with where it comes from: its headline count (findings and readings), the status
    chart and forest plot, one section per source document (claims not run folded, each with its route
    per profile), linking the study that ran each claim; then the statuses that changed since the
    previous ledger (`ledger_history.csv`)."""
    from src.report.ledger_history import changes
    from src.report.ledger_page import SHOWN_ON_INDEX, document_sections, ledger_figures, status_counts
    from src.report.shown_ledger import NONE, choose

    shown = choose(out_dir / "ledger.csv", committed)
    if shown.origin == NONE:
        return [
            "<h2>Reproduction ledger</h2>",
            "<p>No ledger yet (<code>python -m src.run stage=ledger</code>).</p>",
        ]

    def study_href(source: str) -> str | None:
        study = source.removeprefix("study ") if source.startswith("study ") else None
        target = f"sweeps/{study}/index.html" if study else None
        return target if target and (out_dir / target).is_file() else None

    heading = (
        '<a href="ledger.html">Reproduction ledger</a>'
        if (out_dir / "ledger.html").is_file()
        else ("Reproduction ledger")
    )
    section = [
        f"<h2>{heading}</h2>",
        f'<p class="origin">{html.escape(shown.label)}</p>',
        f"<p><b>{html.escape(status_counts(shown.frame))}</b> (findings and readings).</p>",
        *ledger_figures(shown.frame),
        *document_sections(shown.frame, study_href, shown.items_href(out_dir), SHOWN_ON_INDEX, heading="h3"),
    ]
    history = out_dir / "ledger_history.csv"
    if history.is_file():
        changed = changes(pd.read_csv(history, dtype=str))
        if not changed.empty:
            cells = [
                [html.escape(str(r[c])) for c in ("claim", "before", "after")] for _, r in changed.iterrows()
            ]
            when = html.escape(str(changed["written"].iloc[0]))
            section += [
                f"<h3>Changed in the ledger of {when}</h3>",
                html_table(["claim", "before", "now"], cells),
            ]
    return section


def index_page(
    out_dir: Path,
    entries: list[Entry],
    models: Mapping[str, list],
    bench: pd.DataFrame,
    committed: Path | None = None,
) -> str:
    """`index.html`: the ledger's findings, then every report by section (title, profiles, runs, date),
    the benchmark runs and the method pages."""
    stamp = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    body = [
        f"<p>Every report under this folder, built from the logged MLflow runs; generated {stamp}. "
        "Smoke-profile reports check the plumbing only: their numbers mean nothing.</p>"
    ]
    body += _ledger_section(out_dir, committed)
    for section in [*CATEGORIES.values(), STUDIES, OTHER]:
        part = [e for e in entries if e.category == section]
        if not part:
            continue
        rows = []
        for e in part:
            profiles = html.escape(", ".join(e.profiles) or "-")
            if e.smoke:
                profiles += " <b>(smoke: plumbing only)</b>"
            names = sorted(e.manifest.get("methods", {}))
            method_links = ", ".join(_link(method_file(m), m) for m in names) or "-"
            rows.append(
                [
                    _link(f"{e.path}/index.html", e.title),
                    profiles,
                    _number(e.runs, "{:.0f}"),
                    e.date,
                    method_links,
                ]
            )
        body += [
            f"<h2>{html.escape(section)}</h2>",
            html_table(["report", "profile(s)", "runs", "date", "methods"], rows),
        ]
    body.append("<h2>Benchmark</h2>")
    if len(bench):
        newest = _date(bench["start_time"].iloc[0])
        body.append(
            f"<p>{_link(f'{BENCH_DIR}/index.html', 'Benchmark runs')}: {len(bench)} runs, "
            f"newest {newest}.</p>"
        )
    else:
        body.append(f"<p>No benchmark runs (MLflow experiment <code>{BENCH_EXPERIMENT}</code>; "
                    "<code>python -m src.bench denoise --log</code>).</p>")  # fmt: skip
    body.append("<h2>Methods</h2>")
    if models:
        rows = [[_link(method_file(m), m), str(len(records))] for m, records in models.items()]
        body.append(html_table(["method", "reports"], rows))
    else:
        body.append("<p>No report lists a method yet.</p>")
    return page("nrbench reports", body)


def build_site(out_dir: str | Path, committed_ledger: str | Path | None = None) -> dict[str, Any]:
    """Write `index.html`, `methods/*.html` and `bench/index.html` under `out_dir` from what it holds and
    the current MLflow store; the index shows `committed_ledger` (the committed snapshot) until this store's
    ledger has a status. `ledger.html` is the ledger stage's (a DVC output of that stage: never written
    here). Returns the written paths."""
    out_dir = Path(out_dir)
    committed = Path(str(committed_ledger)) if committed_ledger else None
    entries = scan(out_dir)
    models = methods(entries)
    bench = bench_runs()
    # Always written, so that `bench/` is a fixed output (a DVC stage's outs must exist after it runs).
    written = [atomic_write_text(out_dir / BENCH_DIR / "index.html", bench_page(bench))]
    for model, records in models.items():
        written.append(
            atomic_write_text(out_dir / method_file(model), method_page(model, records, out_dir, bench))
        )
    written.append(
        atomic_write_text(out_dir / "index.html", index_page(out_dir, entries, models, bench, committed))
    )
    return {"index": str(out_dir / "index.html"), "files": [str(p) for p in written], "reports": len(entries)}


def refresh_site(out_dir: str | Path, committed_ledger: str | Path | None = None) -> None:
    """`build_site`, its failure logged rather than raised: a report or ledger already written stays
    written when the index cannot be rebuilt."""
    try:
        summary = build_site(out_dir, committed_ledger)
    except Exception as err:
        log.error("site: index not rebuilt (%s: %s)", type(err).__name__, err)
        return
    log.info("site: %d reports -> %s", summary["reports"], summary["index"])
