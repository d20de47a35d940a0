"""Report tables, figures and HTML page built from fixture MLflow runs in a temporary SQLite store."""

import base64
import io
import os
import re
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
from mlflow.entities import Metric, Param
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf
from PIL import Image

from src.errors import ConfigError, DataError
from src.report.build import build_report
from src.report.collect import differing_params, find_runs, keep_latest
from src.report.figures import curve_series
from src.report.table_writers import to_csv, to_latex, to_markdown
from src.report.tables import comparison_table, cost_table, select_metrics
from tests.conftest import compose_config, one_line_error

EXPERIMENT = "nrbench-denoise"
LPIPS_VARIANT = "vgg16-random(seed=0)+lin-uniform"
# model, seed, lr, psnr, relmse, lpips
RUNS = [
    ("kpcn", 0, "0.0001", 30.0, 0.020, 0.20),
    ("kpcn", 1, "0.0001", 31.0, 0.010, 0.22),
    ("dpcn", 0, "0.0001", 29.0, 0.030, 0.25),
    ("resnet", 0, "0.0003", 32.0, 0.015, 0.18),
]


def _log_run(
    client, experiment_id, tmp, model, seed, lr, psnr, relmse, lpips, parent=None, status="FINISHED"
):
    tags = {
        "nrbench.model": model,
        "nrbench.profile": "cpu",
        "nrbench.task": "denoise",
        "nrbench.git_commit": "abc1234",
        "nrbench.lpips_variant": LPIPS_VARIANT,
    }
    if parent is not None:
        tags["mlflow.parentRunId"] = parent
    run_id = client.create_run(experiment_id, tags=tags, run_name=f"{model}-cpu").info.run_id
    params = {
        "model.name": model,
        "seed": str(seed),
        "task.train.lr": lr,
        "task.train.batch": "64",
        "paths.root": f"/somewhere/{run_id}",  # ignored: paths differ per run
        "task.eval.out_dir": f"/out/{run_id}/eval",
    }
    if model == "kpcn":
        params["model.kernel_size"] = "11"  # under the compared axis' group: expected to differ
    metrics = {
        "eval_psnr": psnr,
        "eval_ssim": 0.8 + psnr / 1000,
        "eval_lpips": lpips,
        "eval_relmse": relmse,
        "eval_energy": 0.9 + relmse,
        "eval_psnr_spp4": psnr - 2,
        "eval_psnr_spp16": psnr + 1,
        "param_count": 1000.0 * len(model),
        "train_time_s": 12.5,
        "steps": 30.0,
        "eval_ms_per_image": 3.0,
        "eval_ms_per_mpixel": 40.0,
    }
    history = [
        Metric(f"{split}_loss_{c}", scale / (step + seed + 1), 0, step)
        for split, scale in (("train", 1.0), ("val", 2.0))
        for c in ("diffuse", "specular", "color")
        for step in (10, 20, 30)
    ] + [
        Metric(f"train_step_loss_{c}", 1.5 / (step + 1), 0, step)
        for c in ("diffuse", "color")
        for step in range(1, 31)
    ]
    client.log_batch(
        run_id,
        params=[Param(k, v) for k, v in params.items()],
        metrics=[Metric(k, v, 0, 0) for k, v in metrics.items()] + history,
    )
    png_dir = tmp / f"png-{run_id}"
    png_dir.mkdir()
    rng = np.random.default_rng(seed + len(model))
    reference = np.linspace(0, 255, 16 * 24 * 3).reshape(16, 24, 3).astype(np.uint8)
    for name in ("scene0-00004spp", "scene1-00004spp"):
        noisy = np.clip(reference + rng.normal(0, 40, reference.shape), 0, 255).astype(np.uint8)
        denoised = np.clip(reference + rng.normal(0, 5, reference.shape), 0, 255).astype(np.uint8)
        for kind, image in (("noisy", noisy), ("denoised", denoised), ("reference", reference)):
            Image.fromarray(image).save(png_dir / f"{name}-{kind}.png")
    client.log_artifacts(run_id, str(png_dir), "eval/png")
    # per_image.csv as DenoiseEvaluation writes it: image 0 carries the run's relMSE, image 1 twice it
    per_image = tmp / f"per_image-{run_id}" / "per_image.csv"
    per_image.parent.mkdir()
    pd.DataFrame(
        {
            "scene": ["scene0", "scene1"],
            "spp": [4, 4],
            "psnr": [psnr, psnr - 1],
            "relmse": [relmse, 2 * relmse],
            "energy": [0.9 + 0.02 * seed, 1.0],
            "noisy_energy": [1.01, 0.99],
            "relmse_ratio": [0.1, 0.3 + seed],
        }
    ).to_csv(per_image, index=False)
    client.log_artifact(run_id, str(per_image), "eval")
    client.set_terminated(run_id, status)
    return run_id


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """One SQLite store for the module (creating one costs seconds): 4 finished runs (kpcn twice,
    dpcn, resnet with another lr), a failed run, and a sweep parent whose children are dpcn and resnet."""
    tmp = tmp_path_factory.mktemp("report_store")
    previous = mlflow.get_tracking_uri()
    uri = f"sqlite:///{tmp}/mlflow.db"
    mlflow.set_tracking_uri(uri)
    client = MlflowClient()
    experiment_id = client.create_experiment(EXPERIMENT, artifact_location=(tmp / "mlartifacts").as_uri())
    sweep_dir = tmp / "multirun" / "2024-01-01" / "00-00-00"
    parent = client.create_run(
        experiment_id,
        tags={"nrbench.sweep_parent": "true", "nrbench.sweep_dir": str(sweep_dir)},
        run_name="sweep",
    ).info.run_id
    ids = {}
    for model, seed, lr, psnr, relmse, lpips in RUNS:
        child_of = parent if model in ("dpcn", "resnet") else None
        ids[(model, seed)] = _log_run(
            client, experiment_id, tmp, model, seed, lr, psnr, relmse, lpips, child_of
        )
    _log_run(client, experiment_id, tmp, "broken", 0, "0.0001", 99.0, 0.0, 0.0, status="FAILED")
    client.set_terminated(parent, "FINISHED")
    yield {"tmp": tmp, "uri": uri, "parent": parent, "sweep_dir": sweep_dir, "ids": ids}
    mlflow.set_tracking_uri(previous)


def test_searches_cached_answers_a_repeated_search_from_memory_and_only_inside(store, monkeypatch):
    """The ledger's many identical searches (and experiment lookups) reach the store once each inside
    `searches_cached`, with the same answers; a caller changing its frame does not change the next answer;
    outside, every search reaches the store again (a run logged meanwhile is seen)."""
    from src.report import collect
    from src.report.collect import searches_cached

    mlflow.set_tracking_uri(store["uri"])
    calls = {"search": 0, "experiment": 0}
    search, lookup = mlflow.search_runs, MlflowClient.get_experiment_by_name

    def counted_search(*args, **kwargs):
        calls["search"] += 1
        return search(*args, **kwargs)

    def counted_lookup(self, name):
        calls["experiment"] += 1
        return lookup(self, name)

    monkeypatch.setattr(collect.mlflow, "search_runs", counted_search)
    monkeypatch.setattr(collect.MlflowClient, "get_experiment_by_name", counted_lookup)
    uncached = find_runs({"experiment": EXPERIMENT})
    assert calls == {"search": 1, "experiment": 1}
    with searches_cached():
        first = find_runs({"experiment": EXPERIMENT})
        first.loc[:, "params.model.name"] = "changed by the caller"
        again = find_runs({"experiment": EXPERIMENT})
        kpcn = find_runs({"experiment": EXPERIMENT, "tags": {"nrbench.model": "kpcn"}})
        assert calls == {"search": 3, "experiment": 2}  # the repeat and the second lookup: from memory
    pd.testing.assert_frame_equal(again, uncached)
    assert sorted(kpcn["params.model.name"]) == ["kpcn", "kpcn"]
    find_runs({"experiment": EXPERIMENT})
    assert calls == {"search": 4, "experiment": 3}


def _cfg(store, out, **report):
    cfg = compose_config(
        [
            f"paths.root={store['tmp']}",
            f"paths.run_dir={store['tmp']}/run",
            f"tracking.uri={store['uri']}",
            f"report.out_dir={out}",
        ]
    )
    for key, value in report.items():
        OmegaConf.update(cfg, f"report.{key}", value, merge=False)
    return cfg


def test_find_runs_selects_finished_job_runs(store):
    mlflow.set_tracking_uri(store["uri"])
    runs = find_runs({"experiment": EXPERIMENT})
    assert sorted(runs["params.model.name"]) == ["dpcn", "kpcn", "kpcn", "resnet"]  # no parent, no FAILED
    by_parent = find_runs({"experiment": EXPERIMENT, "parent_run_id": store["parent"]})
    assert sorted(by_parent["params.model.name"]) == ["dpcn", "resnet"]
    by_dir = find_runs({"experiment": EXPERIMENT, "sweep_dir": str(store["sweep_dir"])})
    assert sorted(by_dir["run_id"]) == sorted(by_parent["run_id"])
    by_filter = find_runs(
        {"experiment": EXPERIMENT, "tags": {"nrbench.model": "kpcn"}, "filter": "params.seed = '1'"}
    )
    assert list(by_filter["run_id"]) == [store["ids"][("kpcn", 1)]]
    failed = find_runs({"experiment": EXPERIMENT, "status": "FAILED"})  # what the ledger counts as losses
    assert list(failed["params.model.name"]) == ["broken"]
    with pytest.raises(DataError) as excinfo:
        find_runs({"experiment": EXPERIMENT, "status": "KILLED"})
    one_line_error(excinfo, "report.status='KILLED'", "FINISHED", "FAILED")


def test_keep_latest_drops_older_reruns_of_a_setting_but_keeps_seeds():
    runs = pd.DataFrame(
        {
            "run_id": ["old-kpcn", "dpcn", "kpcn-seed1", "new-kpcn"],
            "params.model.name": ["kpcn", "dpcn", "kpcn", "kpcn"],
            "params.seed": ["0", "0", "1", "0"],
        }
    )  # oldest first, as find_runs sorts them
    assert list(keep_latest(runs, ["model.name"])["run_id"]) == ["dpcn", "kpcn-seed1", "new-kpcn"]
    assert len(keep_latest(runs, ["task.train.lr"])) == 2  # an axis no run logged: one group per seed


def test_group_filter_and_keep_values(store):
    mlflow.set_tracking_uri(store["uri"])
    with pytest.raises(DataError) as excinfo:
        find_runs({"experiment": EXPERIMENT, "group": "dvc"})
    one_line_error(excinfo, "report.group='dvc'", "matched no FINISHED job runs")
    with pytest.raises(DataError) as excinfo:
        find_runs({"experiment": EXPERIMENT, "keep": "newest"})
    one_line_error(excinfo, "report.keep='newest'", "latest")


def test_differing_params_names_lr_only(store):
    mlflow.set_tracking_uri(store["uri"])
    runs = find_runs({"experiment": EXPERIMENT})
    assert differing_params(runs, ["model.name"]) == ["task.train.lr"]
    same_lr = runs[runs["params.task.train.lr"] == "0.0001"]
    assert differing_params(same_lr, ["model.name"]) == []


def test_comparison_table_aggregates_seeds_and_renders(store):
    mlflow.set_tracking_uri(store["uri"])
    runs = find_runs({"experiment": EXPERIMENT})
    table = comparison_table(runs, ["model.name"])
    lpips = f"LPIPS ({LPIPS_VARIANT})"
    assert table.index.name == "model"
    assert list(table.index) == ["kpcn", "dpcn", "resnet"]  # order of first run
    assert [c for c in table.columns if not c.endswith(" std")] == [
        "PSNR",
        "SSIM",
        lpips,
        "relMSE (Bako)",
        "Energy",
        "runs",
    ]
    assert table.loc["kpcn", "PSNR"] == pytest.approx(30.5)
    assert table.loc["kpcn", "PSNR std"] == pytest.approx(np.std([30.0, 31.0], ddof=1))
    assert np.isnan(table.loc["dpcn", "PSNR std"])
    assert list(table["runs"]) == [2, 1, 1]

    md = to_markdown(table)
    assert "| kpcn | 30.50 ± 0.71 |" in md
    assert "**32.00**" in md  # best PSNR: resnet
    assert "**0.0150**" not in md and "**0.015**" in md  # best relMSE (lower is better), {:.4g}
    assert table.loc["dpcn", "Energy"] == pytest.approx(0.93) and "Energy |" in md  # no arrow: 1 is best
    assert "**0.9" not in md  # nor a bold energy
    assert f"{lpips} ↓" in md and "PSNR ↑" in md

    tex = to_latex(table)
    for rule in (r"\toprule", r"\midrule", r"\bottomrule"):
        assert tex.count(rule) == 1
    assert r"\textbf{32.00}" in tex
    assert r"30.50 $\pm$ 0.71" in tex
    escaped = to_latex(comparison_table(runs.assign(**{"params.model.name": "cross_bilateral"})))
    assert r"cross\_bilateral" in escaped

    csv = pd.read_csv(io.StringIO(to_csv(table)))
    assert list(csv["model"]) == ["kpcn", "dpcn", "resnet"]
    assert csv.loc[0, "PSNR"] == pytest.approx(30.5) and csv.loc[0, "PSNR std"] == pytest.approx(0.7071, 1e-3)

    per_spp = comparison_table(runs, ["model.name"], group_by="spp")
    assert {"PSNR 4spp", "PSNR 16spp"} <= set(per_spp.columns)
    assert per_spp.loc["resnet", "PSNR 16spp"] == pytest.approx(33.0)

    cost = cost_table(runs, ["model.name"])
    assert {"params", "train time (s)", "iterations", "ms / image", "ms / MP"} <= set(cost.columns)
    assert "**4,000**" in to_markdown(cost)  # fewest params: kpcn / dpcn (4 letters) tie
    assert "**6,000**" not in to_markdown(cost)
    assert "**12.5" not in to_markdown(cost)  # all runs tie: no best value


def test_the_noisy_input_is_a_row_of_the_quality_tables_never_a_best_method(store):
    """The eval logs the noisy input's scores (`eval_noisy_*`, per spp too): the quality tables show them
    as a "noisy input" row on top, a mean over the runs, and never mark that row best, even where it beats
    every method (a smoke run's KPCN below its input)."""
    mlflow.set_tracking_uri(store["uri"])
    runs = find_runs({"experiment": EXPERIMENT})
    runs = runs.assign(
        **{
            "metrics.eval_noisy_psnr": [40.0, 40.0, 40.0, 41.0],  # beats every model (best is 32)
            "metrics.eval_noisy_relmse": 0.5,
            "metrics.eval_noisy_psnr_spp4": 20.0,
        }
    )
    table = comparison_table(runs, ["model.name"])
    assert list(table.index) == ["noisy input", "kpcn", "dpcn", "resnet"]
    assert table.loc["noisy input", "PSNR"] == pytest.approx(40.25) and table.loc["noisy input", "runs"] == 4
    assert table.loc["noisy input", "PSNR std"] == pytest.approx(0.5)  # runs on different noisy data
    assert np.isnan(table.loc["noisy input", "relMSE (Bako) std"])  # identical: no spread shown
    assert np.isnan(table.loc["noisy input", "SSIM"])  # not logged for the input: "-", never 0
    md = to_markdown(table)
    assert "| noisy input | 40.25 ± 0.50 | - |" in md
    assert "**32.00**" in md and "**40.25" not in md  # resnet is the best method; the input is no method
    assert "**0.015**" in md  # relMSE: 0.5 for the input, best model 0.015
    per_spp = comparison_table(runs, ["model.name"], group_by="spp")
    assert per_spp.loc["noisy input", "PSNR 4spp"] == pytest.approx(20.0)
    assert np.isnan(per_spp.loc["noisy input", "PSNR 16spp"])
    two_axes = comparison_table(runs, ["model.name", "task.train.lr"])
    assert two_axes.index[0] == ("noisy input", "")
    assert list(comparison_table(runs, ["model.name"], noisy=False).index) == ["kpcn", "dpcn", "resnet"]
    assert list(cost_table(runs, ["model.name"]).index) == ["kpcn", "dpcn", "resnet"]


def _embedded_pngs(page):
    return [base64.b64decode(b) for b in re.findall(r'<img [^>]*src="data:image/png;base64,([^"]+)"', page)]


def test_build_report_writes_all_outputs(store, tmp_path, caplog):
    with caplog.at_level("WARNING", logger="nrbench.report"):
        summary = build_report(_cfg(store, tmp_path / "reports"))
    out = tmp_path / "reports" / "denoise"
    assert summary["runs"] == 4 and summary["out_dir"] == str(out)
    assert any("task.train.lr" in r.getMessage() for r in caplog.records)
    assert len(summary["warnings"]) == 1 and "task.train.lr" in summary["warnings"][0]
    names = {p.name for p in out.iterdir()}
    for stem in ("comparison", "cost", "comparison_per_spp", "losses", "per_image", "paired"):
        assert {f"{stem}.md", f"{stem}.tex", f"{stem}.csv"} <= names
    assert {"learning_curves.png", "image_grid.png", "index.html"} <= names
    assert not {"feature_usage.csv", "search_curves.png"} & names  # no filter search among the runs
    assert not [n for n in names if n.startswith(".")]  # no temporary files left
    for name in ("comparison.md", "comparison.tex", "comparison.csv", "cost.md", "index.html"):
        assert "task.train.lr" in (out / name).read_text(), name  # the warning is visible everywhere
    for name in ("cost.md", "cost.csv", "index.html"):  # what each clock covers: under the table, on the page
        assert "Clocks: train time counts the training batches" in (out / name).read_text(), name
    assert "Clocks:" not in (out / "comparison.md").read_text()
    csv = pd.read_csv(out / "comparison.csv", comment="#")
    assert len(csv) == 3
    # per image: rows model x image, each image's scores averaged over the row's runs (kpcn: seeds 0, 1)
    images = pd.read_csv(out / "per_image.csv", comment="#").set_index(["model", "image"])
    models = ("noisy input", "kpcn", "dpcn", "resnet")  # the noisy input's energy (noisy_energy) on top
    assert list(images.index) == [(m, f"scene{i} 4spp") for m in models for i in (0, 1)]
    assert images.loc[("noisy input", "scene1 4spp"), "Energy"] == pytest.approx(0.99)  # 4 runs of 0.99
    assert images.loc[("noisy input", "scene0 4spp"), "runs"] == 4
    assert np.isnan(images.loc[("noisy input", "scene0 4spp"), "PSNR"])  # no noisy_psnr in the csv
    images = images.drop(index="noisy input", level="model")
    assert images.loc[("kpcn", "scene0 4spp"), "Energy"] == pytest.approx(0.91)
    assert images.loc[("kpcn", "scene1 4spp"), "relMSE / noisy"] == pytest.approx(0.8)
    assert images.loc[("kpcn", "scene1 4spp"), "relMSE (Bako)"] == pytest.approx(0.03)
    assert images.loc[("dpcn", "scene1 4spp"), "noisy Energy"] == pytest.approx(0.99)
    assert images.loc[("resnet", "scene0 4spp"), "PSNR"] == pytest.approx(32.0)
    assert list(images["runs"]) == [2, 2, 1, 1, 1, 1]
    assert "Quality per held-out image" in (out / "index.html").read_text()
    paired = pd.read_csv(out / "paired.csv", comment="#").set_index("model")
    # relMSE / noisy is 0.1 and 0.3 + seed for every model: dpcn (seed 0) has the lowest mean; kpcn ties
    # with it on their common items (seed 0), so no p and no finding; resnet has the best PSNR
    assert paired.loc["dpcn", "relMSE / noisy"] == "best" and paired.loc["resnet", "PSNR"] == "best"
    assert paired.loc["kpcn", "relMSE / noisy vs best (ratio)"] == 1.0 and paired.loc["kpcn", "pairs"] == 2
    assert paired.loc["kpcn", "relMSE / noisy"] == "not significant (n = 2)" and pd.isna(
        paired.loc["kpcn", "relMSE / noisy p"]
    )
    assert "paired by seed and held-out image" in (out / "index.html").read_text()
    # Final (step 30) losses, mean over kpcn's two seeds: 1 / (30 + seed + 1) (twice that for validation);
    # validation columns first.
    losses = pd.read_csv(out / "losses.csv", comment="#", index_col=0)
    assert list(losses.columns[:2]) == ["val color", "val color std"]
    assert losses.loc["kpcn", "train specular"] == pytest.approx((1 / 31 + 1 / 32) / 2)
    assert losses.loc["resnet", "val diffuse"] == pytest.approx(2 / 31)

    with Image.open(out / "image_grid.png") as grid:
        # 2 images of 16 x 24 px: (noisy + 3 models + reference) columns; each tile enlarged 16x (its short
        # side to report.min_tile_px = 256) with its whole-image crop below at 1x: 16 * 16 + 16 * 16 rows
        assert grid.width >= 5 * 24 * 16 and grid.height >= 2 * (256 + 256)

    page = (out / "index.html").read_text()
    # the store by its file name, never this machine's path to it
    assert "runs (cpu profile) from sqlite:///mlflow.db," in page and str(store["tmp"]) not in page
    # a legend line under each table for the columns a reader could misread
    assert '<div class="legend">runs: the runs (training seeds) a row averages;' in page
    pngs = _embedded_pngs(page)
    assert len(pngs) == 4
    assert pngs[0] == (out / "quality_by_spp.png").read_bytes()  # the per-spp table drawn
    assert pngs[1] == (out / "quality_cost.png").read_bytes()  # quality against evaluation time
    assert pngs[2] == (out / "learning_curves.png").read_bytes()
    assert pngs[3] == (out / "image_grid.png").read_bytes()
    for data in pngs:
        assert Image.open(io.BytesIO(data)).format == "PNG"
    assert "<b>32.00</b>" in page and "abc1234" in page
    # the store's runs predate the device card: the page says what is missing rather than nothing
    assert "Timings measured on: device, model and threads not recorded (4 runs)." in page
    for run_id in store["ids"].values():
        assert run_id in page


def test_build_report_sweep_children_only(store, tmp_path):
    summary = build_report(_cfg(store, tmp_path, sweep_dir=str(store["sweep_dir"]), name="sweep"))
    assert summary["runs"] == 2
    table = pd.read_csv(tmp_path / "sweep" / "comparison.csv", comment="#")
    assert sorted(table["model"]) == ["dpcn", "resnet"]


def test_every_report_file_reaches_its_name_only_by_an_atomic_rename(store, tmp_path, monkeypatch):
    """A report over other runs, into the directory of an earlier one, killed just before each rename
    (here: every rename into the directory is dropped): every file of the earlier report is intact, so
    none was written in place, and each file of the new one was bound for a rename."""
    out = tmp_path / "reports" / "denoise"
    build_report(_cfg(store, tmp_path / "reports"))
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    renamed = []
    real_replace = os.replace

    def crash_before_rename(src, dst):
        if Path(dst).parent == out:
            renamed.append(Path(dst).name)  # the temporary file is deleted, the old one stays
        else:
            real_replace(src, dst)

    monkeypatch.setattr(os, "replace", crash_before_rename)
    summary = build_report(_cfg(store, tmp_path / "reports", sweep_dir=str(store["sweep_dir"])))
    assert summary["runs"] == 2  # other tables, figures and page than the first report's
    after = {p.name: p.read_bytes() for p in out.iterdir()}
    assert after.keys() == before.keys()  # nothing new, no temporary file left
    assert [name for name in before if after[name] != before[name]] == []  # none written in place
    assert sorted(renamed) == sorted(Path(f).name for f in summary["files"].values())


@pytest.mark.parametrize(
    ("key", "value", "needle"),
    [
        ("filter", "params.`task.train.lr` = '0.5'", "report.filter"),
        ("tags", {"nrbench.profile": "paper"}, "report.tags.nrbench.profile"),
        ("parent_run_id", "0" * 32, "report.parent_run_id"),
        ("sweep_dir", "/no/such/sweep", "report.sweep_dir"),
        ("experiment", "nrbench-nothing", "report.experiment"),
    ],
)
def test_no_matching_runs_is_one_line_error_and_writes_nothing(store, tmp_path, key, value, needle):
    with pytest.raises(DataError) as excinfo:
        build_report(_cfg(store, tmp_path / "reports", **{key: value}))
    one_line_error(excinfo, needle)
    assert not (tmp_path / "reports").exists()


def test_grid_crop_comes_from_task_eval_else_the_named_default():
    """`task.eval.crop_size/crop_zoom` when set (denoise), `DEFAULT_CROP` when the task has none (nerf); a
    value that is not an integer is an error, not silently replaced by the default."""
    from src.report.build import _crop
    from src.report.figures import DEFAULT_CROP

    assert _crop(compose_config(["profile=smoke"])) == (8, 4)  # conf/task_profile/denoise_smoke.yaml
    assert _crop(compose_config(["task=nerf", "profile=smoke"])) == DEFAULT_CROP == (32, 4)
    assert _crop(OmegaConf.create({"report": {}})) == DEFAULT_CROP
    with pytest.raises(ValueError):
        _crop(OmegaConf.create({"task": {"eval": {"crop_size": "big", "crop_zoom": 4}}}))


def test_grid_crop_comes_from_what_the_drawn_runs_logged_first():
    """A sweep's report composes its own profile: the runs' logged crop wins over it (the most common value
    where runs differ), each key on its own; runs that logged none fall back to the report's config."""
    from src.report.build import _crop

    cfg = compose_config(["profile=smoke"])  # its own task.eval: 8 px at x4
    runs = pd.DataFrame(
        {"params.task.eval.crop_size": ["48", "48", "16"], "params.task.eval.crop_zoom": ["3"] * 3}
    )
    assert _crop(cfg, runs) == (48, 3)
    assert _crop(cfg, runs.drop(columns="params.task.eval.crop_zoom")) == (48, 4)
    assert _crop(cfg, pd.DataFrame({"params.task.eval.crop_size": [None, None]})) == (8, 4)
    assert _crop(cfg, pd.DataFrame({"params.model.name": ["kpcn"]})) == (8, 4)


def test_a_table_without_its_metric_specs_is_an_error_not_a_table_without_metrics():
    table = pd.DataFrame({"PSNR": [30.0], "runs": [1]}, index=pd.Index(["kpcn"], name="model"))
    with pytest.raises(ValueError, match="attrs"):
        to_markdown(table)


def test_learning_curves_include_the_per_step_losses(store):
    """The seed thesis plots per-minibatch losses: the figure draws `train_step_loss_*` (faint) beside the
    epoch means of train and validation, when a run logged them."""
    mlflow.set_tracking_uri(store["uri"])
    run_id = store["ids"][("kpcn", 0)]
    series = {name: (xs, ys) for name, xs, ys in curve_series(MlflowClient(), run_id, "diffuse")}
    assert set(series) == {"train_step", "train", "val"}
    assert series["train_step"][0] == list(range(1, 31)) and series["train"][0] == [10, 20, 30]
    assert series["train_step"][1][0] == pytest.approx(1.5 / 2)
    assert set(n for n, *_ in curve_series(MlflowClient(), run_id, "specular")) == {"train", "val"}


def test_tables_by_writes_one_quality_table_per_value_with_the_chosen_columns(store, tmp_path):
    """The NeRF thesis's layout (Tables 6.1-6.5): one table per scene, models as rows, PSNR, LPIPS, SSIM;
    here split by the learning rate, which the fixture runs vary."""
    cfg = _cfg(store, tmp_path, name="by_lr", tables_by="task.train.lr", metrics=["PSNR", "LPIPS", "SSIM"])
    summary = build_report(cfg)
    out = tmp_path / "by_lr"
    tables = {
        lr: pd.read_csv(out / f"comparison_{lr}.csv", comment="#", index_col=0) for lr in ("0.0001", "0.0003")
    }
    assert list(tables["0.0001"].index) == ["kpcn", "dpcn"] and list(tables["0.0003"].index) == ["resnet"]
    lpips = f"LPIPS ({LPIPS_VARIANT})"
    assert [c for c in tables["0.0001"].columns if not c.endswith(" std")] == ["PSNR", lpips, "SSIM", "runs"]
    assert tables["0.0001"].loc["kpcn", "PSNR"] == pytest.approx(30.5)
    assert tables["0.0003"].loc["resnet", lpips] == pytest.approx(0.18)
    assert "Quality: 0.0003" in (out / "index.html").read_text()
    assert not summary["warnings"]  # the split key is not a confounder of the per-value tables
    with pytest.raises(ConfigError) as excinfo:
        build_report(_cfg(store, tmp_path, metrics=["PSNR", "psnr"]))
    one_line_error(excinfo, "report.metrics=['PSNR', 'psnr']", "'relMSE (Bako)'")


# ------------------------------------------------------------------------------ task=filter_search

GP_EXPERIMENT = "nrbench-filter_search"
# (crossover, seed, best fitness per generation, best expression): two settings of the expansion study
GP_RUNS = [
    ("0.45", 0, [0.6, 0.4, 0.3], "exp(-(distance2(normal, normal) + distance1(depth, depth)))"),
    (
        "0.45",
        1,
        [0.6, 0.5, 0.35],
        "exp(-distance2(normal, normal)) * biweight(dot(texture, texture) * nVariance)",
    ),  # noqa: E501
    ("0.9", 0, [0.6, 0.5, 0.55], "exp(-(distance2(pixel, pixel) / 50.0 + distanceMax(color, color)))"),
]


@pytest.fixture(scope="module")
def gp_runs(store):
    """Three finished filter_search runs in the module's store (an experiment of their own): the logged
    per-generation `search_best`, the tag `search.best_expression`, held-out metrics."""
    client = MlflowClient()
    experiment_id = client.create_experiment(
        GP_EXPERIMENT, artifact_location=(store["tmp"] / "mlartifacts-gp").as_uri()
    )
    for crossover, seed, history, expression in GP_RUNS:
        tags = {"nrbench.task": "filter_search", "search.best_expression": expression}
        run_id = client.create_run(experiment_id, tags=tags).info.run_id
        mutation = f"{1 - 0.1 - float(crossover):.2g}" if crossover == "0.45" else "0.09"
        params = {"model.name": "gp_filter", "seed": str(seed), "task.search.replication": "0.1",
                  "task.search.crossover": crossover, "task.search.mutation": mutation}  # fmt: skip
        metrics = [Metric("search_best", v, 0, step) for step, v in enumerate(history)]
        so_far = np.minimum.accumulate(history)
        metrics += [Metric("search_best_so_far", float(v), 0, step) for step, v in enumerate(so_far)]
        metrics += [Metric("eval_psnr", 30.0 - history[-1], 0, 0), Metric("eval_relmse_ratio", 0.5, 0, 0)]
        client.log_batch(run_id, params=[Param(k, v) for k, v in params.items()], metrics=metrics)
        client.set_terminated(run_id, "FINISHED")
    return store


def test_filter_search_runs_report_fitness_search_curves_and_feature_usage(gp_runs, tmp_path):
    """The GP studies' report (Davletaliyev 2016, Table 4.2, Figures 4.6 and 4.8): best fitness (the last
    `search_best`) per setting, the curves of `search_best` per generation, and how often each feature
    occurs in the runs' best expressions (`pixel` and constants are no features)."""
    axes = ["task.search.replication", "task.search.crossover", "task.search.mutation"]
    cfg = _cfg(gp_runs, tmp_path, name="gp", experiment=GP_EXPERIMENT, axes=axes,
               metrics=["min fitness", "best fitness", "relMSE / noisy", "PSNR"])  # fmt: skip
    summary = build_report(cfg)
    out = tmp_path / "gp"
    table = pd.read_csv(out / "comparison.csv", comment="#", index_col=0)
    table = table.set_index("task.search.crossover")
    assert table.loc[0.45, "best fitness"] == pytest.approx((0.3 + 0.35) / 2)
    assert table.loc[0.9, "best fitness"] == pytest.approx(0.55) and table.loc[0.9, "runs"] == 1
    assert table.loc[0.9, "min fitness"] == pytest.approx(0.5)  # the thesis's measure: over all generations
    assert not summary["warnings"]
    usage = pd.read_csv(out / "feature_usage.csv", comment="#", index_col=0)
    # most frequent first, ties by name
    assert list(usage.index) == ["normal", "color", "depth", "texture", "nVariance"]
    assert usage.loc["normal", "occurrences"] == 4 and usage.loc["normal", "runs"] == 2
    assert usage.loc["nVariance", "occurrences"] == 1 and usage.loc["color", "runs"] == 1
    assert "pixel" not in usage.index and usage["share"].sum() == pytest.approx(1.0)
    assert {"feature_usage.md", "feature_usage.tex", "search_curves.png"} <= set(summary["files"])
    page = (out / "index.html").read_text()
    assert "Features of the best expressions" in page and "best fitness per generation" in page
    assert len(_embedded_pngs(page)) == 1  # the search curves; no loss curves, no images


def test_energy_joins_the_denoising_tables_only():
    """Energy is a column of the denoise and filter_search reports (all logged metrics); NeRF's report
    names its columns, so its tables keep the ones they had before energy was logged."""
    assert "Energy" in select_metrics(compose_config().report.metrics)
    assert "Energy" in select_metrics(compose_config(["task=filter_search"]).report.metrics)
    nerf = select_metrics(compose_config(["task=nerf"]).report.metrics)
    assert list(nerf) == ["PSNR", "SSIM", "LPIPS", "relMSE (Bako)", "FLIP"]


def test_each_data_kind_and_task_reports_under_its_own_name():
    """A standalone volumetric job once wrote its report to reports/denoise/, replacing the still-image
    one: the report's default name follows the MLflow experiment (task and data kind)."""
    names = {
        overrides: compose_config(list(overrides)).report.name
        for overrides in [(), ("dataset=volumetric",), ("task=nerf",), ("task=filter_search",)]
    }
    assert names == {
        (): "denoise",
        ("dataset=volumetric",): "denoise-volumetric",
        ("task=nerf",): "nerf",
        ("task=filter_search",): "filter_search",
    }
    still, volume = (compose_config(o) for o in ([], ["dataset=volumetric"]))
    assert still.tracking.experiment.removeprefix("nrbench-") == still.report.name
    assert volume.tracking.experiment.removeprefix("nrbench-") == volume.report.name


def test_the_undefined_column_shows_only_where_an_output_was_undefined():
    runs = pd.DataFrame(
        {
            "params.model.name": ["gp_filter", "gp_filter", "cross_bilateral"],
            "params.seed": ["0", "1", "0"],
            "metrics.eval_psnr": [30.0, 31.0, 29.0],
            "metrics.eval_undefined": [0.0, 0.0, 0.0],
        }
    )
    assert "Undefined" not in comparison_table(runs, noisy=False)  # zeros everywhere: no column
    runs.loc[1, "metrics.eval_undefined"] = 0.25  # one held-out image of four undefined in seed 1
    table = comparison_table(runs, noisy=False)
    assert table.loc["gp_filter", "Undefined"] == pytest.approx(0.125)
    assert table.loc["cross_bilateral", "Undefined"] == 0.0


def test_the_column_legend_explains_each_misreadable_column_once():
    from src.report.tables import COLUMN_NOTES, column_legend

    columns = [
        "PSNR",
        "PSNR std",
        "Energy",
        "Energy 4spp",
        "baseline PSNR",
        "baseline relMSE / noisy",
        "runs",
    ]
    assert column_legend(columns) == [COLUMN_NOTES["Energy"], COLUMN_NOTES["baseline"], COLUMN_NOTES["runs"]]
    assert column_legend(["PSNR", "SSIM"]) == []  # nothing a reader could misread
    random = column_legend(["LPIPS (vgg16-random(seed=0)+lin-uniform)"])
    assert len(random) == 1 and "not comparable with published LPIPS" in random[0]
    trained = column_legend(["LPIPS (vgg16+lin)"])
    assert len(trained) == 1 and "published" not in trained[0]
    # "relMSE / noisy" is not "relMSE (Bako)", and a column only starting like a key's word is not that key
    assert column_legend(["relMSE / noisy"]) == [COLUMN_NOTES["relMSE / noisy"]]
    assert column_legend(["Energyish"]) == []


def test_an_arms_curve_is_the_mean_over_its_seeds_with_their_range():
    from src.report.figures import arm_curve, component_title

    seeds = [([1, 2, 3], [4.0, 2.0, 1.0]), ([1, 2, 3, 4], [2.0, 4.0, 3.0, 9.0]), ([2, 3], [3.0, 2.0])]
    steps, mean, low, high = arm_curve(seeds)
    assert list(steps) == [2, 3]  # the steps every seed logged
    assert list(mean) == pytest.approx([3.0, 2.0]) and list(low) == [2.0, 1.0] and list(high) == [4.0, 3.0]
    steps, mean, low, high = arm_curve([([1], [1.0]), ([2], [3.0])])  # no shared step: each its own
    assert list(steps) == [1, 2] and list(mean) == [1.0, 3.0] and list(low) == list(high) == [1.0, 3.0]
    assert arm_curve([([5, 5, 6], [1.0, 2.0, 3.0])])[1].tolist() == [2.0, 3.0]  # a step logged twice: last
    assert component_title("diffuse") == "diffuse loss" and component_title("loss") == "loss"


def test_the_learning_curves_draw_one_colour_per_arm_not_per_seed(store, tmp_path, monkeypatch):
    import matplotlib.axes

    from src.report.figures import arm_labels, learning_curves

    mlflow.set_tracking_uri(store["uri"])
    runs = find_runs({"experiment": EXPERIMENT})
    assert sorted(arm_labels(runs)) == ["dpcn", "kpcn", "kpcn", "resnet"]  # kpcn: two seeds, one arm
    legends = []
    original = matplotlib.axes.Axes.legend
    monkeypatch.setattr(
        matplotlib.axes.Axes, "legend", lambda self, *a, **k: legends.append(k) or original(self, *a, **k)
    )
    assert learning_curves(runs, tmp_path / "curves.png").is_file()
    (legend,) = legends
    labels = [h.get_label() for h in legend["handles"]]
    assert labels[:3] == ["kpcn (2 seeds)", "dpcn", "resnet"] and labels[3:] == ["per step", "train", "val"]
    assert legend["bbox_to_anchor"][0] > 1  # beside the panels, never over an axis label


def test_small_tiles_are_enlarged_by_a_whole_factor_pixel_for_pixel():
    from src.report.figures import upscale_factor, upscaled

    assert upscale_factor((16, 24), 256) == 16 and upscale_factor((300, 400), 256) == 1
    assert upscale_factor((100, 200), 256) == 3  # 2.56 -> 3: the short side reaches 300
    image = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    big = upscaled(image, 4)
    assert big.shape == (8, 12, 3) and (big[4:8, 8:12] == image[1, 2]).all()  # each pixel a 4 x 4 block
    assert upscaled(image, 1) is image


def test_the_grids_minimum_tile_is_read_from_the_report_config(store, tmp_path):
    build_report(_cfg(store, tmp_path, min_tile_px=48))  # 16 x 24 tiles: 3x, crop at ceil(4 / 3) = 2x
    with Image.open(tmp_path / "denoise" / "image_grid.png") as grid:
        assert grid.width < 5 * 24 * 16 and grid.width >= 5 * 24 * 3


def test_no_text_of_a_report_figure_is_drawn_over_another_or_cut(store, gp_runs, tmp_path, monkeypatch):
    """Every figure the report saves (learning curves of three arms over three loss panels, quality against
    spp and against cost, a filter search's curves) is checked as drawn: no two labels overlap and none
    is cut by its clip box (tests/figure_text.py)."""
    from src.report import figures
    from tests.figure_text import unreadable_texts

    checked, save = {}, figures.save_figure

    def check_then_save(fig, out_png):
        checked[Path(out_png).name] = unreadable_texts(fig)
        return save(fig, out_png)

    monkeypatch.setattr(figures, "save_figure", check_then_save)
    build_report(_cfg(store, tmp_path))
    axes = ["task.search.replication", "task.search.crossover", "task.search.mutation"]
    build_report(_cfg(gp_runs, tmp_path, name="gp", experiment=GP_EXPERIMENT, axes=axes))
    assert set(checked) == {
        "learning_curves.png",
        "quality_by_spp.png",
        "quality_cost.png",
        "search_curves.png",
    }
    assert all(problems == [] for problems in checked.values()), checked


def test_the_per_spp_table_becomes_one_series_per_metric_and_row_in_sample_order():
    from src.report.figures import quality_by_spp, spp_series

    table = pd.DataFrame(
        {
            "PSNR 8spp": [31.0, 29.0],
            "PSNR 8spp std": [0.5, np.nan],
            "PSNR 2spp": [25.0, np.nan],
            "PSNR 2spp std": [0.1, np.nan],
            "SSIM 4spp": [0.9, 0.8],
            "runs": [2, 1],
        },
        index=pd.Index(["kpcn", "dpcn"], name="model"),
    )
    series = spp_series(table)
    assert list(series) == ["PSNR", "SSIM"]
    assert series["PSNR"]["kpcn"] == ([2, 8], [25.0, 31.0], [0.1, 0.5])  # by count, not column order
    assert series["PSNR"]["dpcn"] == ([8], [29.0], [0.0])  # its missing count left out, no std: 0
    assert series["SSIM"]["dpcn"] == ([4], [0.8], [0.0])
    assert spp_series(table[["runs"]]) == {} and quality_by_spp(table[["runs"]], "unused.png") is None


def test_quality_plots_give_each_row_one_colour_in_every_figure_and_skip_a_constant_metric(
    tmp_path, monkeypatch
):
    """The per-spp and the cost figures colour a method alike (the noisy input black, outside the methods'
    cycle, so that kpcn is the first colour in both, as it is the first arm of the learning curves); a
    metric with one value everywhere (Undefined: 0) gets no panel, one with a spread over seeds does."""
    from matplotlib.colors import to_hex

    from src.report import figures

    index = pd.Index(["noisy input", "kpcn", "dpcn"], name="model")
    table = pd.DataFrame(
        {"PSNR 4spp": [20.0, 30.0, 28.0], "Undefined 4spp": [0.0] * 3, "Energy 4spp": [1.0] * 3,
         "Energy 4spp std": [0.0, 0.1, 0.0]},
        index=index,
    )  # fmt: skip
    drawn, save = [], figures.save_figure

    def colours_then_save(fig, out_png):
        legend = next(ax.get_legend() for ax in fig.axes if ax.get_legend())
        handles = [h[0] if isinstance(h, tuple) else h for h in legend.legend_handles]
        names = [t.get_text() for t in legend.get_texts()]
        colours = {n: to_hex(h.get_color()) for n, h in zip(names, handles, strict=True)}
        drawn.append(({ax.get_title() for ax in fig.axes if ax.get_visible()}, colours))
        return save(fig, out_png)

    monkeypatch.setattr(figures, "save_figure", colours_then_save)
    figures.quality_by_spp(table, tmp_path / "spp.png")
    cost = pd.DataFrame({"ms / image": [np.nan, 12.0, 3.0]}, index=index)
    figures.quality_against_cost(table.rename(columns={"PSNR 4spp": "PSNR"}), cost, tmp_path / "cost.png")
    (spp_titles, spp_colours), (_, cost_colours) = drawn
    assert spp_titles == {"PSNR", "Energy"}  # Undefined: 0 everywhere, no panel
    import matplotlib.pyplot as plt

    first, second = (to_hex(c) for c in plt.rcParams["axes.prop_cycle"].by_key()["color"][:2])
    assert spp_colours == {"noisy input": figures.NOISY_COLOR, "kpcn": first, "dpcn": second}
    assert cost_colours == {"kpcn": first, "dpcn": second}
    assert figures.quality_by_spp(table[["Undefined 4spp"]], tmp_path / "none.png") is None
    for n in (8, 10, 12):  # the denoisers sweep compares 8 methods: none may share the noisy input's colour
        colours = figures.row_colors(["noisy input", *(f"m{i}" for i in range(n))])
        methods = {to_hex(c) for row, c in colours.items() if row != "noisy input"}
        assert len(methods) == n and to_hex(colours["noisy input"]) not in methods


def test_quality_against_cost_pairs_each_rows_quality_with_its_time():
    from src.report.figures import cost_points, quality_against_cost

    index = pd.Index(["noisy input", "kpcn", "dpcn"], name="model")
    comparison = pd.DataFrame(
        {"PSNR": [25.0, 30.0, 28.0], "PSNR std": [np.nan, 0.5, np.nan], "LPIPS": [0.1, 0.05, 0.07]},
        index=index,
    )
    cost = pd.DataFrame({"ms / image": [np.nan, 12.0, 3.0]}, index=index)
    points = cost_points(comparison, cost)
    assert list(points) == ["PSNR"]  # LPIPS is not among the drawn columns; SSIM is absent
    psnr = points["PSNR"]
    assert list(psnr.index) == ["kpcn", "dpcn"]  # the noisy input has no time
    assert psnr.loc["kpcn"].tolist()[:2] == [12.0, 30.0] and psnr.loc["kpcn", "std"] == 0.5
    assert cost_points(comparison, cost.rename(columns={"ms / image": "other"})) == {}
    assert quality_against_cost(comparison[["LPIPS"]], cost, "unused.png") is None


def test_quality_against_cost_names_crowded_points_in_a_legend_not_over_each_other(tmp_path, monkeypatch):
    """Six methods at nearly one cost and quality (a sweep of seeds of one setting, say): each gets its own
    colour and marker, named once in a legend beside the panels; no name is written over another."""
    from src.report import figures
    from tests.figure_text import unreadable_texts

    index = pd.Index([f"kpcn lr={lr}" for lr in (1, 2, 3, 4, 5, 6)], name="model")
    comparison = pd.DataFrame({"PSNR": 30 + 0.01 * np.arange(6), "SSIM": [0.9] * 6}, index=index)
    cost = pd.DataFrame({"ms / image": 12 + 0.01 * np.arange(6)}, index=index)
    drawn, save = {}, figures.save_figure

    def check_then_save(fig, out_png):
        legend = fig.axes[-1].get_legend()
        drawn["legend"] = [t.get_text() for t in legend.get_texts()]
        drawn["styles"] = {(h.get_color(), h.get_marker()) for h in legend.legend_handles}
        drawn["problems"] = unreadable_texts(fig)
        drawn["scale"] = fig.axes[0].get_xscale()
        return save(fig, out_png)

    monkeypatch.setattr(figures, "save_figure", check_then_save)
    assert figures.quality_against_cost(comparison, cost, tmp_path / "q.png") == tmp_path / "q.png"
    assert drawn["legend"] == list(index) and len(drawn["styles"]) == 6
    assert drawn["problems"] == [] and drawn["scale"] == "linear"  # 12 to 12.05 ms: a log axis crowds
    # the cost axis turns logarithmic only above COST_LOG_RATIO (10) between the slowest and the fastest
    for slowest, scale in (
        (120.0, "linear"),
        (120.5, "log"),
        (1200.0, "log"),
        (1300.0, "log"),
        (12000.0, "log"),
    ):
        cost["ms / image"] = np.linspace(12.0, slowest, 6)
        figures.quality_against_cost(comparison, cost, tmp_path / "q.png")
        assert drawn["scale"] == scale and drawn["problems"] == [], (slowest, drawn)


def test_unreadable_texts_finds_overlapping_and_cut_labels_and_passes_apart_ones():
    """The check the figure tests rely on, on both sides: two names at one point overlap, the same names
    far apart do not; a name clipped to its axes and running out of them is cut; tick labels beyond the
    view limits (kept, not drawn) are not counted."""
    import matplotlib.pyplot as plt

    from tests.figure_text import unreadable_texts

    def figure(second_at, clip=False):
        fig, ax = plt.subplots(figsize=(4, 3))
        ax.set_xlim(0, 10)
        ax.set_ylim(0, 10)
        ax.text(2, 2, "first method")
        ax.text(*second_at, "second method", clip_on=clip)
        return fig

    crowded, apart, cut = figure((2.2, 2.1)), figure((2, 8)), figure((9.5, 8), clip=True)
    assert unreadable_texts(crowded) == ["'first method' over 'second method'"]
    assert unreadable_texts(apart) == []
    assert unreadable_texts(cut) == ["'second method' cut by its clip box"]
    for fig in (crowded, apart, cut):
        plt.close(fig)


@pytest.mark.parametrize(
    ("mean", "std", "fmt", "texts"),
    [
        (0.1577, 0.03916, "{:.4g}", ("0.158", "0.039")),  # the mean rounded to the std's second digit
        (0.002647, 7.259e-05, "{:.4g}", ("0.002647", "0.000073")),  # plain decimals, never 7.259e-05
        (33.5, 0.15, "{:.2f}", ("33.50", "0.15")),  # the format already ends at the std's digit: kept
        (33.5, 0.015, "{:.2f}", ("33.50", "0.015")),  # a finer std: the mean keeps its format
        (143.7, 22.7, "{:.1f}", ("144", "23")),
        (6249.0, 1116.3, "{:.1f}", ("6200", "1100")),  # two significant digits above the decimal point
        (392498.0, 1234.5, "{:,.0f}", ("392,500", "1,200")),  # thousands separators kept on both
        (392498.0, 0.0, "{:,.0f}", ("392,498", "0")),  # deterministic: the format, no rounding
        (35.09, 0.0, "{:.2f}", ("35.09", "0.00")),
        (1.5e-07, 1e-08, "{:.4g}", ("1.5e-07", "1e-08")),  # scientific means keep their format
        (float("nan"), 0.1, "{:.4g}", ("-", "0.1")),
    ],
)
def test_mean_and_std_print_without_float_noise(mean, std, fmt, texts):
    from src.report.table_writers import mean_std_text

    assert mean_std_text(mean, std, fmt) == texts


def test_a_tables_cells_print_mean_and_std_through_the_same_rule():
    from src.report.table_writers import cells

    table = pd.DataFrame(
        {"relMSE (Bako)": [0.1577, 0.2], "relMSE (Bako) std": [0.03916, 0.01], "runs": [6, 1]},
        index=pd.Index(["kpcn", "oidn"], name="model"),
    )
    table.attrs["metrics"] = {"relMSE (Bako)": ("eval_relmse", False, "{:.4g}")}
    _, _, rows = cells(table)
    assert rows[0][1][:2] == ("0.158", "0.039")
    assert rows[1][1][:2] == ("0.2", None)  # one run: no std, the mean in its own format


def test_the_losses_table_leaves_out_methods_that_log_no_loss():
    """A sweep of learned denoisers and filters: the filter (no loss logged) gets no row of dashes; the
    learned rows keep their mean and std, and the table its metric specs (the writers need them)."""
    from src.report.tables import loss_table

    runs = pd.DataFrame(
        {
            "params.model.name": ["kpcn", "kpcn", "oidn"],
            "params.seed": ["0", "1", "0"],
            "metrics.val_loss_color": [0.1, 0.3, np.nan],
            "metrics.train_loss_color": [0.05, np.nan, np.nan],  # one seed without its train loss
            "run_id": ["a", "b", "c"],
        }
    )
    table = loss_table(runs)
    assert list(table.index) == ["kpcn"] and table.loc["kpcn", "val color"] == pytest.approx(0.2)
    assert table.loc["kpcn", "train color"] == pytest.approx(0.05)
    assert set(table.attrs["metrics"]) == {"val color", "train color"}
    # a row with any of the losses stays: the third run (another model) logged its validation loss only
    some = loss_table(runs.assign(**{"params.model.name": ["kpcn", "kpcn", "resnet"],
                                     "metrics.val_loss_color": [0.1, 0.3, 0.2]}))  # fmt: skip
    assert list(some.index) == ["kpcn", "resnet"] and pd.isna(some.loc["resnet", "train color"])


@pytest.mark.parametrize(
    ("tile_width", "crop_side", "zoom", "k", "expected"),
    [
        (256, 128, 4, 4, 2),  # the denoisers sweep: 64 px images x4, a 32 px crop: twice, to fill the tile
        (256, 256, 4, 1, 4),  # the configured zoom when it is more than filling needs
        (72, 72, 4, 3, 2),  # ceil(4 / 3): the crop already spans the tile
        (256, 40, 4, 8, 6),  # filling: 6 x 40 = 240 <= 256, 7 x 40 would overflow
        (10, 0, 1, 1, 10),  # a degenerate window never divides by zero
    ],
)
def test_the_grids_crop_fills_its_tiles_width_at_least_at_the_configured_zoom(
    tile_width, crop_side, zoom, k, expected
):
    from src.report.figures import crop_zoom

    assert crop_zoom(tile_width, crop_side, zoom, k) == expected
