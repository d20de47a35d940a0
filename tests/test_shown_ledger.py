"""Which ledger the site shows (src/report/shown_ledger.py), its figures (src/report/ledger_figures.py), the
numbers the forest plot draws (`ledger_page.effect_numbers`) and the route's run time (`ledger.run_time`)."""

import io
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from src.report.claims import Rule
from src.report.collect import REPOSITORY, display_path, store_name
from src.report.ledger import duration_text, run_time
from src.report.ledger_figures import forest_plot, forest_rows, status_chart, status_table
from src.report.ledger_page import COLUMNS, document_sections, effect_numbers, write_ledger_page
from src.report.shown_ledger import COMMITTED, LOCAL, NONE, choose, runs_summary
from src.report.site import build_site
from src.report.verdicts import Verdict

HEADER = (
    "ledger written 2026-11-28 19:08:56 UTC by nrbench at commit 91e56642348e from a store of 4 counted runs"
)
CARD = "AMD EPYC, 2 threads, fp32"


def _row(claim, status, document="Doc A", category="finding", **extra):
    row = {c: "-" for c in COLUMNS}
    measured_on = f"{CARD} (6 runs); FLOPs and memory not logged" if status != "not run" else "-"
    row |= dict(claim=claim, status=status, document=document, category=category, measured_on=measured_on)
    row |= dict(profile="cpu" if status != "not run" else "-", numbers=f"why {claim}")
    return row | extra


def _write(path: Path, rows, header: str = "") -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    text = pd.DataFrame(rows, columns=list(COLUMNS)).to_csv(index=False)
    path.write_text((f"# {header}\n" if header else "") + text)
    return path


RAN = [
    _row(
        "a1",
        "reproduced",
        estimate="2.0",
        low="1.5",
        high="2.5",
        scale="factor",
        reference="10",
        items_csv="items/a1.csv",
    ),
    _row(
        "a2", "not reproduced", estimate="-1", low="-2", high="-0.5", scale="psnr", items_csv="items/a2.csv"
    ),
    _row("a3", "not run"),
    _row("b1", "not run", document="Doc B"),
    _row("t1", "reproduced", document="Doc B", category="target", estimate="1", low="1", high="1"),
]


def test_this_stores_ledger_is_shown_once_it_has_a_status(tmp_path):
    local = _write(tmp_path / "reports" / "ledger.csv", RAN)
    committed = _write(tmp_path / "docs" / "ledger.csv", RAN[:1], HEADER)
    shown = choose(local, committed)
    assert shown.origin == LOCAL and list(shown.frame["claim"]) == ["a1", "a2", "a3", "b1", "t1"]
    assert shown.label == "This store's ledger (ledger.csv)" and shown.folder == local.parent


def test_the_committed_snapshot_is_shown_while_this_store_has_no_status(tmp_path):
    local = _write(tmp_path / "reports" / "ledger.csv", [_row("a1", "not run"), _row("a2", "not run")])
    committed = _write(tmp_path / "docs" / "ledger.csv", RAN, HEADER)
    shown = choose(local, committed)
    assert shown.origin == COMMITTED and len(shown.frame) == 5 and shown.folder == committed.parent
    # which file (by name: outside the repository), why, its header, and the profiles and machines of its runs
    assert shown.label == (
        "Committed snapshot ledger.csv (this store's ledger has no status yet): " + HEADER + "; profiles cpu "
        f"(3 claims); measured on {CARD}"
    )
    # without a local ledger at all, the reason says so
    assert "(this store has no ledger)" in choose(tmp_path / "none.csv", committed).label


def test_a_committed_snapshot_without_a_status_does_not_replace_this_stores_ledger(tmp_path):
    local = _write(tmp_path / "reports" / "ledger.csv", [_row("a1", "not run")])
    committed = _write(tmp_path / "docs" / "ledger.csv", [_row("a1", "not run")], HEADER)
    shown = choose(local, committed)
    assert shown.origin == LOCAL and shown.label.endswith(": no claim has runs yet")
    assert choose(tmp_path / "absent.csv", None).origin == NONE
    assert choose(tmp_path / "absent.csv", tmp_path / "absent_too.csv").origin == NONE


def test_a_file_is_named_relative_to_the_repository_or_by_its_name():
    assert display_path(REPOSITORY / "docs" / "results" / "ledger.csv") == "docs/results/ledger.csv"
    assert display_path(Path("/somewhere/else/ledger.csv")) == "ledger.csv"


def test_the_runs_summary_counts_profiles_and_lists_each_machine_once():
    frame = pd.DataFrame(
        [
            _row("a", "reproduced", measured_on=f"{CARD} (6 runs); median FLOPs / px 1,000"),
            _row(
                "b",
                "reproduced",
                profile="paper",
                measured_on=f"{CARD} (2 runs); H100, 16 threads, bf16 (1 run)",
            ),
            _row("c", "not run", measured_on="ignored (9 runs)"),
        ]
    )
    assert (
        runs_summary(frame)
        == f"profiles cpu (1 claims), paper (1 claims); measured on {CARD}, H100, 16 threads, bf16"
    )


def test_the_items_link_leads_from_the_page_to_the_snapshots_folder_when_the_file_is_there(tmp_path):
    committed = _write(tmp_path / "docs" / "results" / "ledger.csv", RAN, HEADER)
    (committed.parent / "items").mkdir()
    (committed.parent / "items" / "a1.csv").write_text("seed,a_minus_b\n0,1\n")
    href = choose(tmp_path / "reports" / "ledger.csv", committed).items_href(tmp_path / "reports")
    assert href("items/a1.csv") == "../docs/results/items/a1.csv"
    assert href("items/a2.csv") is None  # no such file: no link


def test_the_ledger_page_groups_by_document_folds_the_not_run_and_never_prints_an_empty_table(tmp_path):
    committed = _write(tmp_path / "docs" / "ledger.csv", RAN, HEADER)
    (committed.parent / "items").mkdir()
    (committed.parent / "items" / "a1.csv").write_text("seed,a_minus_b\n0,1\n")
    page = write_ledger_page(tmp_path / "reports", committed).read_text()
    assert page.count('<a href="../docs/items/a1.csv">per-replicate differences</a>') == 1  # a2 has none
    doc_a, doc_b = page.split("<h2>Doc A</h2>")[1].split("<h2>Doc B</h2>")
    assert doc_a.count("<tr>") == 1 + 2 and "1 claim not run" in doc_a and "<li><code>a3</code>" in doc_a
    # Doc B: its finding did not run (folded), its target ran (a table, not counted in the headline)
    assert doc_b.count("<tr>") == 1 + 1 and "<li><code>b1</code>" in doc_b and "why b1" in doc_b
    assert "1 reproduced, 1 not reproduced, 2 not run</b> (findings and readings)" in page
    assert page.count('<img alt="') == 2  # the status chart and the forest plot
    assert "Committed snapshot ledger.csv" in page
    # a document whose claims all did not run gets its folded list and no table
    only_not_run = document_sections(pd.DataFrame([_row("x", "not run", document="Doc X")]))
    assert not any("<table" in part for part in only_not_run) and any("<details>" in p for p in only_not_run)


def test_the_site_shows_the_committed_snapshot_without_a_local_ledger(tmp_path):
    committed = _write(tmp_path / "docs" / "ledger.csv", RAN, HEADER)
    reports = tmp_path / "reports"
    reports.mkdir()
    build_site(reports, committed)
    index = (reports / "index.html").read_text()
    assert "Committed snapshot ledger.csv (this store has no ledger)" in index
    assert "<h3>Doc A</h3>" in index and "<code>a1</code>" in index
    assert '<img alt="claims by document' in index
    # ledger.html is the ledger stage's output: the site neither writes it nor links it while it is absent
    assert not (reports / "ledger.html").exists() and 'href="ledger.html"' not in index
    _write(reports / "ledger.csv", RAN)
    (reports / "ledger.html").write_text("the ledger stage's page")
    build_site(reports, committed)
    assert (reports / "ledger.html").read_text() == "the ledger stage's page"
    index = (reports / "index.html").read_text()
    assert "This store&#x27;s ledger (ledger.csv)" in index and '<a href="ledger.html">' in index


# --- figures ------------------------------------------------------------------------------------------


def _png(data: bytes) -> Image.Image:
    return Image.open(io.BytesIO(data))


def test_the_status_table_counts_findings_and_readings_by_document_and_status():
    counts = status_table(pd.DataFrame(RAN))
    assert list(counts.index) == ["Doc A", "Doc B"]  # in order of appearance
    assert list(counts.columns) == ["reproduced", "not reproduced", "not run"]  # STATUSES order; t1 left out
    assert counts.loc["Doc A"].tolist() == [1, 1, 1] and counts.loc["Doc B"].tolist() == [0, 0, 1]


def test_the_forest_rows_are_the_claims_with_an_interval_factor_first():
    rows = forest_rows(pd.DataFrame(RAN))
    assert list(rows["claim"]) == ["a1", "t1", "a2"]  # factor ("a1"), then "-" (t1's scale), then psnr
    assert rows.set_index("claim").loc["a1", "reference"] == 10.0
    assert math.isnan(rows.set_index("claim").loc["a2", "reference"])
    no_interval = pd.DataFrame([_row("x", "reproduced", estimate="nan", low="nan", high="nan", scale="psnr")])
    assert forest_rows(no_interval).empty and forest_plot(no_interval) is None
    assert forest_plot(pd.DataFrame([_row("x", "reproduced")]).drop(columns=["scale"])) is None  # old CSV


def test_no_text_of_the_ledger_figures_is_drawn_over_another(monkeypatch):
    """The status chart and the forest plot, with a few claims and with thirty: no two labels overlap
    (claim names, axis labels, the legend beside the panels, the title) and none is cut."""
    from src.report import ledger_figures
    from tests.figure_text import unreadable_texts

    found, to_bytes = [], ledger_figures.png_bytes

    def check_then_save(fig):
        found.append(unreadable_texts(fig))
        return to_bytes(fig)

    monkeypatch.setattr(ledger_figures, "png_bytes", check_then_save)
    more = pd.DataFrame(
        [_row(f"c{i}", "reproduced", estimate="1", low="0.5", high="2", scale="factor") for i in range(30)]
    )
    for frame in (pd.DataFrame(RAN), more):
        assert status_chart(frame) is not None and forest_plot(frame) is not None
    assert found == [[]] * 4


def test_the_figures_are_pngs_that_fit_the_page():
    frame = pd.DataFrame(RAN)
    for png in (status_chart(frame), forest_plot(frame)):
        image = _png(png)
        assert image.format == "PNG" and 400 < image.width <= 1400 and image.height > 100
    # taller with more claims: a row per claim
    more = pd.DataFrame(
        [_row(f"c{i}", "reproduced", estimate="1", low="0.5", high="2", scale="factor") for i in range(30)]
    )
    assert _png(forest_plot(more)).height > _png(forest_plot(frame)).height
    assert status_chart(pd.DataFrame(columns=["claim", "status"])) is None


@pytest.mark.parametrize(
    ("log", "kind", "size", "tolerance", "expected"),
    [
        (True, "better", 10.0, 0.0, {"scale": "factor", "estimate": math.e, "reference": 10.0}),
        (False, "better", 1.5, 0.0, {"scale": "psnr", "estimate": 1.0, "reference": 1.5}),
        (True, "better", 0.0, 0.0, {"reference": math.nan, "tolerance": math.nan}),
        (True, "better", 1.0, 0.0, {"reference": math.nan}),  # a factor of 1: no size (as `_published`)
        (False, "better", 0.5, 0.0, {"reference": 0.5}),  # a difference below 1 is a size
        (True, "comparable", 0.0, math.log(1.25), {"tolerance": 1.25, "reference": math.nan}),
        (False, "not_worse", 0.0, 0.5, {"tolerance": 0.5, "low": 0.0, "high": 2.0}),
    ],
)
def test_effect_numbers_are_on_the_printed_scale(log, kind, size, tolerance, expected):
    claim = SimpleNamespace(log=log, metric="psnr", rule=Rule(kind=kind, size=size, tolerance=tolerance))
    verdict = Verdict("reproduced", "", estimate=1.0, low=0.0, high=2.0)
    numbers = effect_numbers(SimpleNamespace(claim=claim, verdict=verdict))
    if log:
        assert numbers["low"] == pytest.approx(1.0) and numbers["high"] == pytest.approx(math.e**2)
    for key, value in expected.items():
        if isinstance(value, float) and math.isnan(value):
            assert math.isnan(numbers[key]), key
        else:
            assert numbers[key] == pytest.approx(value) if isinstance(value, float) else numbers[key] == value


def test_run_time_sums_the_wall_times_and_names_the_machines():
    start = pd.to_datetime(["2026-01-01 10:00", "2026-01-01 11:00"], utc=True)
    runs = pd.DataFrame(
        {
            "start_time": start,
            "end_time": start + pd.to_timedelta([20, 30], unit="min"),
            "tags.nrbench.device_name": "AMD EPYC",
            "tags.nrbench.threads": "2",
            "tags.nrbench.precision": "fp32",
        }
    )
    assert run_time(runs) == f"measured: 50 min of run time on {CARD} (2 runs)"
    assert run_time(pd.DataFrame()) == "not measured in this store"
    still_running = runs.assign(end_time=pd.to_datetime([None, None], utc=True))
    assert run_time(still_running) == "not measured in this store"


@pytest.mark.parametrize(
    ("seconds", "text"),
    [
        (0, "0 s"),
        (89, "89 s"),
        (90, "2 min"),
        (89 * 60, "89 min"),
        (90 * 60, "1.5 h"),
        (np.float64(7200), "2.0 h"),
    ],
)
def test_durations_print_in_the_unit_a_reader_wants(seconds, text):
    assert duration_text(seconds) == text


@pytest.mark.parametrize(
    ("uri", "shown"),
    [
        (f"sqlite:///{REPOSITORY}/mlflow.db", "sqlite:///mlflow.db"),
        ("sqlite:////scratch/me/runs/mlflow.db", "sqlite:///mlflow.db"),
        (f"file://{REPOSITORY}/mlruns", "file:///mlruns"),
        ("/scratch/me/mlruns", "mlruns"),
        ("http://me:secret@10.0.0.5:5000", "http://10.0.0.5:5000"),
        ("https://tracking.example.org", "https://tracking.example.org"),
    ],
)
def test_a_store_is_printed_without_a_machine_path_or_credentials(uri, shown):
    assert store_name(uri) == shown
