"""The report site (src/report/site.py): the index linking every report, study, the ledger and the
benchmark runs; the method pages; the smoke banner and the best expressions of the report pages; and the
browser check (scripts/check_site.py) in headless Chromium on a site built from the fixture store of
tests/test_report.py."""

import html
import re
import shutil
import subprocess
import sys
from pathlib import Path

import mlflow
import pandas as pd
import pytest
from mlflow.entities import Metric, Param
from mlflow.tracking import MlflowClient

from src.report.build import build_report
from src.report.ledger_page import COLUMNS
from src.report.noisebase_table import HEADING as NOISEBASE_HEADING
from src.report.site import BENCH_EXPERIMENT, SMOKE_NOTE, build_site
from tests.test_report import GP_EXPERIMENT, _cfg, _log_run, gp_runs, store  # noqa: F401 (fixtures)

ROOT = Path(__file__).resolve().parents[1]
VOLUMETRIC = "nrbench-denoise-volumetric"


def test_the_bench_experiment_is_the_one_the_benchmarks_log_to():
    from src.bench.bench_log import EXPERIMENT

    assert BENCH_EXPERIMENT == EXPERIMENT


@pytest.fixture(scope="module")
def site(gp_runs, tmp_path_factory):  # noqa: F811 (the imported fixture)
    """A site from the fixture store: the still-image report (cpu), a smoke-profile volumetric report
    (its own experiment), a filter-search study under sweeps/, a ledger and one benchmark run."""
    runs = gp_runs
    tmp = tmp_path_factory.mktemp("site")
    client = MlflowClient()
    vol = client.create_experiment(VOLUMETRIC, artifact_location=(runs["tmp"] / "mlartifacts-vol").as_uri())
    for model, seed, psnr in (("kpcn", 0, 26.85), ("dpcn", 0, 27.5)):
        run_id = _log_run(client, vol, runs["tmp"], model, seed, "0.0001", psnr, 0.05, 0.3)
        client.set_tag(run_id, "nrbench.profile", "smoke" if model == "kpcn" else "cpu")
        client.log_batch(run_id, metrics=[Metric("eval_noisy_psnr", 34.08, 0, 0)])
        # scored with metrics.protocol=noisebase too (at 4 spp): the report's Noisebase table
        nb_psnr = {"kpcn": 23.25, "dpcn": 21.75}[model]
        client.log_batch(run_id, metrics=[Metric("eval_nb_psnr_spp4", nb_psnr, 0, 0)])
    bench = client.create_experiment(BENCH_EXPERIMENT, artifact_location=(runs["tmp"] / "mlart-b").as_uri())
    run_id = client.create_run(bench, tags={"nrbench.profile": "cpu", "nrbench.device": "cpu"}).info.run_id
    client.log_batch(
        run_id, params=[Param("bench", "denoise")], metrics=[Metric("seconds_kpcn", 0.0125, 0, 0)]
    )
    client.log_text(run_id, "kpcn 12.5 ms per frame\n", "bench/report.txt")
    client.set_terminated(run_id, "FINISHED")

    # held-out relMSE / noisy in the reverse order of the search fitness (0.3, 0.35, 0.55 last generation):
    # the best-expressions table sorts by the held-out number; one run has its eval's expression tag
    gp = mlflow.search_runs(experiment_names=[GP_EXPERIMENT], output_format="pandas")
    for run_id, fitness in zip(gp["run_id"], gp["metrics.search_best"], strict=True):
        held_out = {0.3: 0.6, 0.35: 0.4, 0.55: 0.5}[round(fitness, 2)]
        client.log_batch(run_id, metrics=[Metric("eval_relmse_ratio", held_out, 0, 1)])
        if fitness == pytest.approx(0.35):
            client.set_tag(
                run_id, "search.evaluated_expression", "exp(-distance2(normal, normal) * 2.0000000000000004)"
            )

    reports = tmp / "reports"
    build_report(_cfg(runs, reports, name="denoise"))
    build_report(_cfg(runs, reports, name="volumetric", experiment=VOLUMETRIC))
    axes = ["task.search.replication", "task.search.crossover", "task.search.mutation"]
    build_report(_cfg(runs, reports, name="sweeps/gp_rules", experiment=GP_EXPERIMENT, axes=axes))
    claims = [
        dict(claim="c1", category="finding", profile="cpu", status="reproduced", unit="seeds", seeds="6"),
        dict(claim="c2", category="target", profile="cpu", status="reproduced", unit="rounds", seeds="0"),
        dict(claim="gpu_claim", category="finding", profile="-", status="not run", numbers="needs a GPU"),
    ]
    claims[0]["from"] = claims[1]["from"] = "study gp_rules"
    ledger = pd.DataFrame([{c: row.get(c, "-") for c in COLUMNS} for row in claims], columns=list(COLUMNS))
    ledger.to_csv(reports / "ledger.csv", index=False)
    history = pd.DataFrame(
        {
            "written": ["w1", "w1", "w2", "w2"],
            "claim": ["c1", "gpu_claim", "c1", "gpu_claim"],
            "status": ["not distinguishable", "not run", "reproduced", "not run"],
        }
    )
    history.to_csv(reports / "ledger_history.csv", index=False)
    (reports / "ledger.html").write_text("<!DOCTYPE html><title>ledger</title><p>ledger</p>")
    summary = build_site(reports)
    return {"reports": reports, "summary": summary, **runs}


def _links(page: str) -> list[str]:
    return re.findall(r'<a href="([^"]+)"', page)


def test_the_index_links_every_report_study_ledger_bench_and_method(site):
    reports = site["reports"]
    index = (reports / "index.html").read_text()
    links = _links(index)
    for target in (
        "denoise/index.html",
        "volumetric/index.html",
        "sweeps/gp_rules/index.html",
        "ledger.html",
        "bench/index.html",
        "methods/kpcn.html",
        "methods/dpcn.html",
        "methods/resnet.html",
    ):
        assert target in links, target
        assert (reports / target).is_file(), target
    # sections by experiment, each entry with its profile(s), run count and date
    assert index.index("Still-image denoisers") < index.index("Volumetric sequences") < index.index("Studies")
    row = re.search(r'<tr><td><a href="volumetric/index.html">.*?</tr>', index, re.S).group(0)
    assert "cpu, smoke" in row and "plumbing only" in row and "<td>2</td>" in row
    row = re.search(r'<tr><td><a href="denoise/index.html">.*?</tr>', index, re.S).group(0)
    assert "<td>cpu</td>" in row and "<td>4</td>" in row and "smoke" not in row
    assert re.search(r"\d{4}-\d\d-\d\d \d\d:\d\d UTC", row)
    # the ledger's findings, its study linked
    assert "1 reproduced, 1 not run" in index  # the target c2 is not counted as a seed's finding
    assert "Changed in the ledger of w2" in index
    assert "<tr><td>c1</td><td>not distinguishable</td><td>reproduced</td></tr>" in index
    assert "gpu_claim</td><td>not run" not in index  # unchanged claims are not listed
    assert '<a href="sweeps/gp_rules/index.html">study gp_rules</a>' in index
    # the claims not run are folded, each with its reason
    folded = re.search(r"<details><summary>1 claim not run: .*?</details>", index, re.S).group(0)
    assert "<code>gpu_claim</code>" in folded and "needs a GPU" in folded
    assert "gpu_claim</code><details>" not in index  # not a row of the table of claims that ran
    assert "1 runs" in index  # the benchmark entry


def test_a_method_page_shows_config_size_speed_bench_and_its_table_rows(site):
    page = (site["reports"] / "methods" / "kpcn.html").read_text()
    assert '<a href="../denoise/index.html">' in page and '<a href="../volumetric/index.html">' in page
    assert "<code>model.kernel_size</code>" in page and "<code>11</code>" in page  # its config
    assert "4,000" in page and "12.5" in page and "3.0" in page  # params, train s, ms / image
    assert "12.50" in page  # the benchmark's 0.0125 s per frame, in ms
    # its rows of the comparison table (mean of seeds 0, 1: 30.5 dB), the noisy input beside them
    assert "30.5" in page and "Quality" in page
    # mean ± std as on the report page: the std to two significant digits (seeds 30 and 31 dB: 0.7071...)
    assert "30.5 ± 0.71" in page and "0.7071" not in page
    assert SMOKE_NOTE in page  # one of its reports is a smoke run
    dpcn = (site["reports"] / "methods" / "dpcn.html").read_text()
    assert "12.50" not in dpcn and "Benchmark" not in dpcn  # no bench run timed dpcn
    # the Noisebase protocol's table (a section of the volumetric report): each method its own row, the
    # published NPPD row on neither page
    heading = html.escape(NOISEBASE_HEADING)
    for model, own, other in (("kpcn", "23.25", "21.75"), ("dpcn", "21.75", "23.25")):
        text = (site["reports"] / "methods" / f"{model}.html").read_text()
        section = text[text.index(heading) :]
        assert own in section and other not in section and "NPPD" not in section and "29.35" not in section


def test_a_smoke_report_says_so_at_its_top_and_shows_the_noisy_input(site):
    vol = (site["reports"] / "volumetric" / "index.html").read_text()
    assert vol.index(SMOKE_NOTE) < vol.index("<h1>")
    assert f"{SMOKE_NOTE} (smoke-profile runs here: 1 of 2)" in vol
    assert '<tr class="noisy"><td class="key">noisy input</td><td class="num">34.08</td>' in vol
    assert "<b>34.08</b>" not in vol and "<b>27.50</b>" in vol  # the best method, not the input
    assert SMOKE_NOTE not in (site["reports"] / "denoise" / "index.html").read_text()
    assert vol.count("<table>") == vol.count('<div class="scroll"><table>') > 3  # each table scrolls
    # the image grid's tiles carry their PSNR; the heading says so
    assert "each tile&#x27;s PSNR against the reference" in vol


def test_the_filter_search_report_lists_the_best_expressions_with_held_out_numbers(site):
    out = site["reports"] / "sweeps" / "gp_rules"
    table = pd.read_csv(out / "best_expressions.csv")
    # GP_RUNS: the last generation's best 0.35, 0.55, 0.3 -> held-out PSNR 30 - that; relMSE / noisy as set
    assert list(table["held-out relMSE / noisy"]) == pytest.approx([0.4, 0.5, 0.6])  # best held-out first
    assert list(table["held-out PSNR"]) == pytest.approx([29.65, 29.45, 29.7])
    assert list(table["search fitness (min)"]) == pytest.approx([0.35, 0.5, 0.3])
    # the expression the eval scored wins over the search's best; the others say they were not scored
    assert (
        table.loc[0, "expression"] == "exp(-distance2(normal, normal) * 2.0000000000000004)"
    )  # the CSV: as logged
    assert list(table["scored on"]) == ["held-out split"] + ["search only (no eval)"] * 2
    assert table["expression"].str.contains(r"distance2\(pixel, pixel\)").any()  # infix as logged
    page = (out / "index.html").read_text()
    assert "best expressions (infix)" in page and "<code>exp(" in page
    # the page: its constants without float noise (src/gp/text.py::compact)
    assert "<code>exp(-distance2(normal, normal) * 2)</code>" in page and "2.0000000000000004" not in page
    assert "best fitness per generation" in page  # the curves


def _check(reports: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "check_site.py"), str(reports), *args],
        capture_output=True,
        text=True,
        timeout=120,
    )


def test_the_site_loads_in_chromium_and_a_broken_image_or_link_fails_the_check(site, browser, tmp_path):
    result = _check(site["reports"], "--screenshots", str(tmp_path / "shots"))
    assert result.returncode == 0, result.stdout + result.stderr
    pages = int(re.search(r"ok, (\d+) pages", result.stdout).group(1))
    assert pages == 10  # index, 3 reports, ledger, bench, 4 method pages (gp_filter too)
    assert {p.name for p in (tmp_path / "shots").iterdir()} == {"index.png", "report.png"}

    broken = tmp_path / "broken"
    shutil.copytree(site["reports"], broken)
    page = broken / "denoise" / "index.html"
    text = page.read_text()
    page.write_text(re.sub(r'src="data:image/png;base64,[^"]+"', 'src="missing.png"', text, count=1))
    (broken / "methods" / "resnet.html").unlink()
    ledger = broken / "ledger.html"
    ledger.write_text(ledger.read_text() + '<div style="width: 3000px">a table that does not scroll</div>')
    # a thumbnail, a table without rows and a label its box cuts, on a page of their own (linked)
    import base64
    import io

    from PIL import Image

    def png(width: int, height: int) -> str:
        buffer = io.BytesIO()
        Image.new("RGB", (width, height)).save(buffer, format="PNG")
        return "data:image/png;base64," + base64.b64encode(buffer.getvalue()).decode()

    (broken / "bad.html").write_text(
        f'<!DOCTYPE html><html><body><img alt="small grid" src="{png(148, 136)}">'
        f'<img alt="wide enough" src="{png(300, 100)}">'
        "<table><thead><tr><th>claim</th></tr></thead><tbody></tbody></table>"
        "<table><tbody><tr><td>a row</td></tr></tbody></table>"
        '<div style="width: 40px; overflow: hidden; white-space: nowrap">reference image</div>'
        '<div style="width: 40px; overflow: auto; white-space: nowrap">scrolls: shown</div></body></html>'
    )
    index = broken / "index.html"
    index.write_text(index.read_text().replace("</body>", '<a href="bad.html">bad</a></body>'))
    result = _check(broken)
    assert result.returncode == 1, result.stdout
    assert "bad.html: image below 256 px: small grid (148x136 px)" in result.stdout
    assert "wide enough" not in result.stdout  # its longer side is 300 px
    assert result.stdout.count("bad.html: empty table") == 1 and "empty table: claim" in result.stdout
    assert result.stdout.count("bad.html: clipped text") == 1 and "div: reference image" in result.stdout
    assert "ledger.html: page " in result.stdout and "px wider than a 1280 px window" in result.stdout
    assert "denoise/index.html: image did not load: missing.png" in result.stdout
    assert "link to a missing page: methods/resnet.html" in result.stdout


def test_grid_tiles_carry_their_psnr_and_radiance_fields_start_at_the_reference(store, tmp_path):  # noqa: F811
    """A denoising grid reads noisy | denoised | reference, a radiance field's reference | rendered; each
    tile but the reference is labelled with its PSNR against the reference (the skimage PSNR of the
    evaluation, on the PNGs shown)."""
    import numpy as np
    from PIL import Image

    from src.io.images import SEPARATOR_PX
    from src.metrics.image import psnr
    from src.report.figures import GRID_HEADINGS, _panels, image_grid

    client = MlflowClient()
    experiment = client.create_experiment("nerf-grid", artifact_location=(tmp_path / "art").as_uri())
    rng = np.random.default_rng(0)
    reference = rng.integers(0, 256, (12, 16, 3), dtype=np.uint8)
    ids = {}
    for model, sigma in (("nerf", 20), ("mipnerf", 5)):
        run_id = client.create_run(experiment).info.run_id
        client.log_batch(run_id, params=[Param("model.name", model), Param("seed", "0")])
        folder = tmp_path / model
        folder.mkdir()
        rendered = np.clip(reference + rng.normal(0, sigma, reference.shape), 0, 255).astype(np.uint8)
        Image.fromarray(reference).save(folder / "lego-r_0-reference.png")
        Image.fromarray(rendered).save(folder / "lego-r_0-rendered.png")
        client.log_artifacts(run_id, str(folder), "eval/png")
        client.set_terminated(run_id, "FINISHED")
        ids[model] = (run_id, rendered)
    runs = pd.DataFrame(
        {"run_id": [ids[m][0] for m in ids], "params.model.name": list(ids), "params.seed": ["0", "0"]}
    )
    chosen = {m: (ids[m][0], {"lego-r_0": {"rendered", "reference"}}) for m in ids}
    panels = _panels("lego-r_0", chosen, tmp_path / "dl")
    assert [label.split(" ")[0] for label, _ in panels] == ["reference", "nerf", "mipnerf"]
    for (label, image), model in zip(panels[1:], ids, strict=True):
        expected = psnr(ids[model][1] / 255.0, reference / 255.0)
        assert label == f"{model} {expected:.2f} dB"
        assert np.array_equal(image, ids[model][1])
    grid = image_grid(runs, tmp_path / "grid.png", 1, ["model.name"], 4, 2, min_tile=1)  # pixel for pixel
    assert grid.heading == GRID_HEADINGS["rendered"] and "reference | rendered" in grid.heading
    with Image.open(grid.path) as image:
        # the 4 px crop at 16 // 4 = 4x (not the configured 2x): as wide as its 16 px tile, below a separator
        assert image.size == (3 * 16 + 2 * SEPARATOR_PX, 12 + SEPARATOR_PX + 4 * 4)
        first = np.asarray(image.convert("RGB"))[:12, :16]  # the first tile, its crop box drawn on it
    same = (first == reference).all(axis=-1).mean()
    assert same > 0.5 and (first == ids["nerf"][1]).all(axis=-1).mean() < 0.2


def test_a_sequence_frame_in_the_grid_says_which_frame_and_the_report_follows_a_crop_through_time(
    store,  # noqa: F811
    tmp_path,
):
    import numpy as np
    from PIL import Image

    from src.report.figures import _panels, temporal_grid

    client = MlflowClient()
    experiment = client.create_experiment("sequence-grid", artifact_location=(tmp_path / "art").as_uri())
    run_id = client.create_run(experiment).info.run_id
    client.log_batch(run_id, params=[Param("model.name", "unet_kpcn"), Param("seed", "0")])
    folder = tmp_path / "png"
    folder.mkdir()
    rng = np.random.default_rng(0)
    for frame in range(3):
        for kind in ("noisy", "denoised", "reference"):
            image = rng.integers(0, 256, (20, 24, 3), dtype=np.uint8)
            Image.fromarray(image).save(folder / f"cloud-f{frame:04d}-00004spp-{kind}.png")
    client.log_artifacts(run_id, str(folder), "eval/png")
    client.set_terminated(run_id, "FINISHED")
    chosen = {
        "unet_kpcn": (
            run_id,
            {f"cloud-f{f:04d}-00004spp": {"noisy", "denoised", "reference"} for f in range(3)},
        )
    }
    panels = _panels("cloud-f0002-00004spp", chosen, tmp_path / "dl")
    assert panels[-1][0] == "reference, frame 2"
    runs = pd.DataFrame({"run_id": [run_id], "params.model.name": ["unet_kpcn"], "params.seed": ["0"]})
    strip = temporal_grid(runs, tmp_path / "temporal.png", ["model.name"], crop_size=8, zoom=2, min_tile=8)
    with Image.open(strip) as image:  # rows noisy, unet_kpcn, reference; a column per frame; 16-px cells
        assert image.size == (3 * 16 + 2 * 2, 3 * 16 + 2 * 2)
    # by default a cell is at least half a grid tile: an 8-px crop is enlarged 16x, to 128 px
    with Image.open(temporal_grid(runs, tmp_path / "t2.png", ["model.name"], crop_size=8, zoom=2)) as image:
        assert image.size == (3 * 128 + 2 * 2, 3 * 128 + 2 * 2)
