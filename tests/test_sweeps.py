"""Sweeps (conf/sweep, linked as sweeps/): every study and launcher config composes, the Optuna sweeper's
search space and objective, and real smoke sweeps that end in a report with one row per setting."""

import csv
import os
import shutil
import subprocess
import sys

import mlflow
import numpy as np
import pandas as pd
import pytest
import yaml
from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.utils import get_class
from omegaconf import OmegaConf

from hydra_plugins.nrbench_optuna_sweeper.optuna_sweeper import (
    OptunaSweeper,
    distribution,
    objective_value,
    search_space,
)
from src import _scale
from src.errors import ConfigError
from src.train.checkpoint import load_checkpoint
from tests.conftest import CONF_DIR, ROOT, compose_config, one_line_error, smoke_config

STUDIES = {
    "denoisers",
    "shared_vs_separate",
    "whitening",
    "nerf_variants",
    "nerf_thesis",
    "lr_search",
    "gp_expansion",
    "gp_population",
    "gp_search_cost",
    "kernel_vs_direct",
    "gp_bias_guard",
    "gp_rules",
    "unet_vs_kpcn",
    "feature_selection",
    "temporal_loss",
    "noisebase",
}
GROUPS = {"model", "task", "dataset"}


def compose_sweep(name, overrides=()):
    """The job config of `python -m src.run -m +sweep=<name> [overrides]`, with its `hydra` section."""
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("config", overrides=[f"+sweep={name}", *overrides], return_hydra_config=True)


def swept(cfg):
    """(key, values-or-sweep) of the sweeper's `params`, parsed as Hydra parses them."""
    params = [f"{k}={v}" for k, v in cfg.hydra.sweeper.params.items()]
    return {o.get_key_element(): o for o in OverridesParser.create().parse_overrides(params)}


def values(override) -> list[str]:
    """The values a sweep override takes: every element of a sweep, or its one value."""
    return list(override.sweep_string_iterator()) if override.is_sweep_override() else [override.value()]


def test_every_study_has_one_sweep_file_under_sweeps():
    assert {p.stem for p in (ROOT / "sweeps").glob("*.yaml")} == STUDIES
    assert (ROOT / "sweeps").resolve() == (ROOT / "conf" / "sweep").resolve()


@pytest.mark.parametrize("profile", ["smoke", "cpu", "paper"])
@pytest.mark.parametrize("name", sorted(STUDIES))
def test_sweep_composes_with_its_report_and_every_swept_value(name, profile):
    cfg = compose_sweep(name, [f"profile={profile}"])
    assert cfg.report.name == f"sweeps/{name}"
    assert str(cfg.hydra.sweep.dir).startswith(f"multirun/sweeps/{name}/")
    for axis in cfg.report.axes:  # a key of the config (its value may be null, e.g. feature_selection.size)
        assert OmegaConf.select(cfg, str(axis), default=KeyError) is not KeyError, axis
    for key, override in swept(cfg).items():
        group = key.lstrip("+") in GROUPS or key.startswith("+")  # a config group (or one added: +name)
        # Each choice composes as a job would, at smoke and paper (the cpu profile's are what the other
        # tests compose all the time).
        if group and profile != "cpu":
            for choice in override.sweep_string_iterator():
                job = compose_sweep(name, [f"profile={profile}", f"{key}={choice}"])
                assert key.startswith("+") or job[key].name == choice
        elif not group:  # a key of the config, possibly null (task.search.crop: whole images)
            assert OmegaConf.select(cfg, key, default=KeyError) is not KeyError, key


@pytest.mark.parametrize("name", sorted(STUDIES - {"lr_search", "nerf_thesis"}))
def test_grid_studies_run_several_training_seeds_on_fixed_data(name):
    cfg = compose_sweep(name)
    seeds = list(swept(cfg)["seed"].sweep_string_iterator())
    assert len(seeds) >= 3
    assert cfg.data_seed == 0 and "data_seed" not in swept(cfg)  # the data stay; only training varies


def test_the_nerf_thesis_sweep_is_the_thesis_s_experiment():
    """Grujčić 2023, Sec. 6: three models x its five nerf_synthetic scenes, one run each, trained as
    `profile=thesis`; per-scene tables of PSNR, LPIPS, SSIM (Tables 6.1-6.5)."""
    cfg = compose_sweep("nerf_thesis", ["dataset.root=/data/nerf_synthetic"])
    params = swept(cfg)
    assert list(params["model"].sweep_string_iterator()) == ["nerf", "mipnerf", "refnerf"]
    scenes = list(params["task.scene"].sweep_string_iterator())
    assert scenes == ["lego", "materials", "drums", "chair", "ship"] and set(scenes) <= set(
        cfg.dataset.scenes
    )
    assert params["seed"].value() == 0  # the thesis reports one run per cell
    assert (cfg.profile_name, cfg.task.name, cfg.dataset.name, cfg.task.train.max_steps) == (
        "thesis",
        "nerf",
        "blender",
        1_000_000,
    )
    assert cfg.report.tables_by == "task.scene" and list(cfg.report.metrics) == ["PSNR", "LPIPS", "SSIM"]


def test_ablations_fix_what_the_seed_thesis_fixed():
    shared = compose_sweep("shared_vs_separate")
    whitening = compose_sweep("whitening")
    assert shared.model.name == whitening.model.name == "resnet"
    assert list(swept(shared)["model.shared"].sweep_iterator()) == [True, False]
    assert whitening.model.shared is False
    assert list(swept(whitening)["model.whiten"].sweep_iterator()) == [True, False]
    nerf = compose_sweep("nerf_variants")
    assert nerf.task.name == "nerf" and nerf.report.columns_by == "task.scene"
    assert values(swept(nerf)["task.scene"]) == list(nerf.compare.nerf.scenes)
    assert set(nerf.compare.nerf.scenes) <= set(nerf.dataset.scenes)


def test_lr_search_uses_the_optuna_sweeper_on_a_validation_loss():
    cfg = compose_sweep("lr_search")
    sweeper = cfg.hydra.sweeper
    assert get_class(sweeper._target_).__name__ == OptunaSweeper.__name__
    assert sweeper.objective.startswith("train.val_") and sweeper.direction == "minimize"
    distributions, fixed = search_space([f"{k}={v}" for k, v in sweeper.params.items()])
    assert set(distributions) == {"task.train.lr", "task.train.batch_size"} and fixed == []
    assert distributions["task.train.lr"].log


# Davletaliyev 2016, Table 4.2: (replication, crossover, mutation) -> the best expression's relMSE.
TABLE_4_2 = {(0.10, 0.15, 0.75): 0.98257, (0.10, 0.45, 0.45): 0.377417, (0.33, 0.33, 0.34): 0.70105,
             (0.01, 0.90, 0.09): 1.16676}  # fmt: skip
EXPANSION = ("replication", "crossover", "mutation")


def test_the_gp_expansion_sweep_is_table_4_2_s_four_settings():
    """Four settings (not the product of the three keys), each a valid job whose task.search has them."""
    cfg = compose_sweep("gp_expansion")
    assert cfg.task.name == "filter_search" and cfg.model.name == "gp_filter"
    override = swept(cfg)["task.search"]
    settings = [tuple(float(d[k]) for k in EXPANSION) for d in override.sweep_iterator()]
    assert settings == list(TABLE_4_2) and all(sum(s) == pytest.approx(1.0) for s in settings)
    # a job's setting is merged into task.search (the other search keys stay the profile's)
    job = compose_sweep("gp_expansion", [f"task.search={next(override.sweep_string_iterator())}"])
    assert tuple(job.task.search[k] for k in EXPANSION) == settings[0]
    assert job.task.search.islands == cfg.task.search.islands
    assert list(cfg.report.axes) == [f"task.search.{k}" for k in EXPANSION]
    assert list(cfg.report.metrics)[:2] == ["min fitness", "best fitness"] and "PSNR" in cfg.report.metrics


def test_the_gp_bias_guard_sweep_is_the_thesis_fitness_against_one_guard_weight():
    """Two arms (w = 0, the thesis's fitness, and 0.5) x three seeds, reported with the energy column."""
    cfg = compose_sweep("gp_bias_guard")
    assert cfg.task.name == "filter_search" and cfg.task.search.bias_guard == 0.0
    params = swept(cfg)
    assert [float(v) for v in values(params["task.search.bias_guard"])] == [0.0, 0.5]
    assert values(params["seed"]) == ["0", "1", "2"]
    assert list(cfg.report.axes) == ["task.search.bias_guard"] and "Energy" in cfg.report.metrics
    assert compose_sweep("gp_bias_guard", ["task.search.bias_guard=0.5"]).task.search.bias_guard == 0.5


def test_the_gp_rules_sweep_is_the_thesis_rules_against_the_first_ones():
    """Two arms merged into task.search (the defaults, the thesis's, first), three seeds each."""
    cfg = compose_sweep("gp_rules")
    params = swept(cfg)
    arms = [dict(d) for d in params["task.search"].sweep_iterator()]
    rules = ("vector_pairs", "crossover_points", "shares_count", "color_variance")
    assert arms[0] == {k: cfg.task.search[k] for k in rules}  # the thesis's rules are the defaults
    assert arms[1] == dict(zip(rules, ("mixed", "type_first", "draws", False), strict=True))
    assert values(params["seed"]) == ["0", "1", "2"] and "Energy" in cfg.report.metrics
    job = compose_sweep("gp_rules", [f"task.search={list(params['task.search'].sweep_string_iterator())[1]}"])
    assert job.task.search.vector_pairs == "mixed" and job.task.search.hall_of_fame == 10


def test_the_noisebase_study_runs_every_denoiser_that_reads_noisebase_sets():
    """Issue 35: the U-Net KPCN, KPCN, DPCN, the residual KPCN, OIDN and the cross-bilateral filter side by
    side on dataset=noisebase; not the GP expressions, which read a buffer Noisebase lacks (visibility)."""
    cfg = compose_sweep("noisebase")
    assert cfg.dataset.name == "noisebase" and cfg.report.axes == ["model.name"]
    models = values(swept(cfg)["model"])
    assert sorted(models) == sorted(["unet_kpcn", "kpcn", "dpcn", "resnet", "oidn", "cross_bilateral"])
    assert not [m for m in models if m.startswith("gp_")]


def test_the_gp_population_sweep_scales_with_the_profile():
    """Figure 4.7's axis at 1/2, 1, 2 and 4 times the profile's population per island (at least 1)."""
    cfg = compose_sweep("gp_population", ["profile=cpu"])
    values = [int(v) for v in swept(cfg)["task.search.population"].sweep_string_iterator()]
    assert cfg.task.search.population == 16 and values == [8, 16, 32, 64]
    assert list(cfg.report.axes) == ["task.search.population"]
    assert _scale(4, 0.5, 1, 2, 4) == "2,4,8,16" and _scale(100, 0.5, 4) == "50,400" and _scale(1, 0.5) == "1"


@pytest.mark.parametrize(
    ("profile", "generations", "crops"), [("cpu", [10, 20], [64, 128]), ("paper", [100, 200], [360, 720])]
)
def test_the_gp_search_cost_sweep_halves_the_generations_and_the_image_height(profile, generations, crops):
    """Figures 4.2-4.3's axes: half and all of the profile's generations, a centre crop of half and all of
    the dataset's image height, read from the composed profile (not typed in the sweep)."""
    cfg = compose_sweep("gp_search_cost", [f"profile={profile}"])
    params = swept(cfg)
    assert [int(v) for v in params["task.search.generations"].sweep_string_iterator()] == generations
    assert [int(v) for v in params["task.search.crop"].sweep_string_iterator()] == crops
    assert cfg.task.search.generations == generations[1] and cfg.dataset.height == crops[1]
    assert list(cfg.report.axes) == ["task.search.generations", "task.search.crop"]


@pytest.mark.parametrize(
    ("launcher", "target", "values"),
    [
        ("parallel", "JoblibLauncher", {"n_jobs": 2}),
        (
            "slurm",
            "RequeueingSlurmLauncher",
            {"gpus_per_node": 1, "max_num_timeout": 3, "signal_delay_s": 120},
        ),
    ],
)
def test_launcher_configs_compose_and_name_their_plugin(launcher, target, values):
    cfg = compose_sweep("whitening", [f"hydra/launcher={launcher}"])
    assert get_class(cfg.hydra.launcher._target_).__name__ == target
    assert {k: cfg.hydra.launcher[k] for k in values} == values
    if launcher == "slurm":  # submitit's SLURM launcher, with the requeue recorded (src/launch/requeue.py)
        bases = [f"{c.__module__}.{c.__name__}" for c in get_class(cfg.hydra.launcher._target_).__mro__]
        assert "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher" in bases
        assert cfg.hydra.launcher._target_.startswith("hydra_plugins.")  # Hydra instantiates no other


def test_tracking_uri_follows_mlflow_tracking_uri(monkeypatch):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://mlflow.cluster:5000")
    cfg = compose_sweep("denoisers", [f"paths.root={ROOT}"])
    assert cfg.tracking.uri == "http://mlflow.cluster:5000"


# ------------------------------------------------------------------------------ Optuna sweeper


def _override(text):
    return OverridesParser.create().parse_overrides([text])[0]


def test_hydra_sweep_syntax_becomes_optuna_distributions():
    log_float = distribution(_override("lr=tag(log, interval(1e-5, 1e-2))"))
    assert (log_float.low, log_float.high, log_float.log) == (1e-5, 1e-2, True)
    integer = distribution(_override("blocks=int(interval(2, 8))"))
    assert (integer.low, integer.high, integer.log) == (2, 8, False)
    assert type(integer).__name__ == "IntDistribution"
    stepped = distribution(_override("blocks=range(2, 9, 2)"))
    assert (stepped.low, stepped.high, stepped.step) == (2, 8, 2)
    assert distribution(_override("bs=8,16,32")).choices == (8, 16, 32)
    assert distribution(_override("loss=choice(l1, l2)")).choices == ("l1", "l2")


def test_search_space_keeps_fixed_values_and_lets_the_command_line_win():
    distributions, fixed = search_space(["lr=interval(0.1, 1.0)", "seed=3", "bs=8,16", "bs=32"])
    assert set(distributions) == {"lr"} and fixed == ["seed=3", "bs=32"]


def test_objective_is_read_from_the_job_result_with_a_clear_error():
    result = {"train": {"val_loss_color": 0.25}, "eval": {}}
    assert objective_value(result, "train.val_loss_color") == 0.25
    with pytest.raises(ConfigError) as err:
        objective_value(result, "train.val_loss_specular")
    one_line_error(err, "hydra.sweeper.objective=train.val_loss_specular", "val_loss_color")
    with pytest.raises(ConfigError) as err:
        objective_value({"train": {"v": float("nan")}}, "train.v")
    one_line_error(err, "nan")


def test_bad_sweeper_settings_name_the_key():
    good = {"objective": "train.x", "n_trials": 2, "n_jobs": 1, "seed": 0}
    with pytest.raises(ConfigError) as err:
        OptunaSweeper(direction="down", sampler="tpe", **good)
    one_line_error(err, "hydra.sweeper.direction=down")
    with pytest.raises(ConfigError) as err:
        OptunaSweeper(direction="minimize", sampler="grid", **good)
    one_line_error(err, "hydra.sweeper.sampler=grid")


# ------------------------------------------------------------------------------ real smoke sweeps


def sweep(args, data, out):
    """`python -m src.run -m ...` at the smoke profile on the shared smoke dataset; outputs under `out`.
    Returns its output (stdout, then stderr)."""
    env = {**os.environ, "NRBENCH_DATA_DIR": str(data), "MLFLOW_TRACKING_URI": f"sqlite:///{out}/mlflow.db"}
    cmd = [
        sys.executable,
        "-m",
        "src.run",
        "-m",
        *args,
        "profile=smoke",
        f"hydra.sweep.dir={out}/sweep",
        f"tracking.artifact_root={out}/mlartifacts",
        f"report.out_dir={out}/reports",
    ]
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return result.stdout + result.stderr


def read_csv(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def read_table(path):
    """A report table's CSV rows as strings, its leading `# ` note lines skipped."""
    return pd.read_csv(path, comment="#", dtype=str).to_dict("records")


def method_rows(path):
    """The rows of a report's quality table but the noisy input's (first column `noisy input`, on top
    where the runs logged the input's scores: docs/report-site.md)."""
    return [r for r in read_csv(path) if next(iter(r.values())) != "noisy input"]


def test_whitening_sweep_in_parallel_reports_one_row_per_setting(smoke_data, tmp_path):
    sweep(["+sweep=whitening", "seed=0,1", "hydra/launcher=parallel"], smoke_data, tmp_path)
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path}/mlflow.db")
    report = tmp_path / "reports" / "sweeps" / "whitening"
    assert read_csv(report / "comparison.csv")[0]["model.whiten"] == "noisy input"
    rows = method_rows(report / "comparison.csv")
    assert sorted(r["model.whiten"] for r in rows) == ["False", "True"]
    assert all(r["runs"] == "2" for r in rows)
    # The two seeds trained differently (their PSNRs differ), and each row is their mean ± sample std.
    runs = mlflow.search_runs(
        experiment_names=["nrbench-denoise"], filter_string="attributes.status = 'FINISHED'"
    )
    runs = runs[runs["params.seed"].notna()]
    for r in rows:
        mine = runs[runs["params.model.whiten"] == r["model.whiten"]]
        assert sorted(mine["params.seed"]) == ["0", "1"]
        psnr = mine["metrics.eval_psnr"].to_numpy()
        assert psnr[0] != psnr[1], r
        assert float(r["PSNR"]) == pytest.approx(psnr.mean(), rel=1e-6)
        assert float(r["PSNR std"]) == pytest.approx(psnr.std(ddof=1), rel=1e-6)
    losses = read_csv(report / "losses.csv")
    assert len(losses) == 2 and {"val specular", "train specular"} <= set(losses[0])
    assert (report / "learning_curves.png").is_file() and (report / "index.html").is_file()
    # Quality against time: every epoch's validation loss at the training clock of that step, per arm.
    client = mlflow.MlflowClient()
    timed = read_table(report / "quality_vs_time.csv")
    assert (
        sorted(r["model.whiten"] for r in timed) == ["False", "True"]
        and (report / "quality_vs_time.png").is_file()
    )
    for r in timed:
        mine = runs[runs["params.model.whiten"] == r["model.whiten"]]
        finals = []
        for run_id in mine["run_id"]:
            clock = {m.step: m.value for m in client.get_metric_history(run_id, "train_time_s")}
            loss = sorted((m.step, m.value) for m in client.get_metric_history(run_id, "val_loss_color"))
            assert [step for step, _ in loss] == sorted(clock)[: len(loss)] and len(loss) >= 2
            assert list(clock.values()) == sorted(clock.values())  # the clock never falls back
            finals.append(loss[-1][1])
        assert float(r["final validation loss (colour)"]) == pytest.approx(np.mean(finals), rel=1e-6)
        assert 0 <= float(r["reached"]) <= 1
    # The cost card: each stage's peak memory and the evaluation's achieved GFLOP/s.
    assert (runs["metrics.train_peak_host_mb"] > 100).all() and (
        runs["metrics.eval_peak_host_mb"] > 100
    ).all()
    assert (runs["metrics.eval_flops_per_pixel"] > 0).all() and (runs["metrics.eval_gflops"] > 0).all()
    cost = read_table(report / "cost.csv")
    assert all(float(r["GFLOP/s (eval)"]) > 0 and float(r["host MB (train)"]) > 100 for r in cost)
    # Samples saved: the smoke data's ladder read per arm and input count.
    saved = read_table(report / "samples_saved.csv")
    assert {(r["model.whiten"], r["spp"]) for r in saved} == {
        (w, s) for w in ("False", "True") for s in ("4", "16")
    }
    assert all(float(r["spp-equivalent"]) > 0 and r["runs"] == "2" for r in saved)
    # the method page shows the mean over the method's runs of their logged spp-equivalent and speed-up
    page = (tmp_path / "reports" / "methods" / "resnet.html").read_text()
    assert "<th>spp-equivalent</th>" in page and "<th>speed-up</th>" in page
    assert f"<td>{runs['metrics.eval_spp_equivalent'].mean():.1f}</td>" in page
    # The sweep rewrote the ledger: the whitening claim found this sweep's runs, at a profile (smoke)
    # where it means nothing.
    ledger = {r["claim"]: r for r in read_csv(tmp_path / "reports" / "ledger.csv")}
    whitening = ledger["whitening_hurts_specular"]
    assert whitening["status"] == "not run" and "runs at smoke only" in whitening["numbers"]


@pytest.mark.slow
def test_six_jobs_on_two_workers_share_one_sqlite_store_without_a_database_error(smoke_data, tmp_path):
    """Two joblib workers write one SQLite MLflow store at once (experiment creation, runs, params,
    metrics, artifacts): every job's run ends FINISHED with its test metrics, under one parent run."""
    args = ["hydra/launcher=parallel", "hydra.launcher.n_jobs=2", "model=cross_bilateral,oidn", "seed=0,1,2"]
    out = sweep(args, smoke_data, tmp_path)
    assert "database is locked" not in out and "Traceback" not in out, out[-3000:]
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path}/mlflow.db")
    runs = mlflow.search_runs(experiment_names=["nrbench-denoise"])
    parents = runs[runs["tags.mlflow.parentRunId"].isna()]
    children = runs[runs["tags.mlflow.parentRunId"].notna()]
    assert len(parents) == 1 and set(parents["status"]) == {"FINISHED"}
    assert len(children) == 6 and set(children["status"]) == {"FINISHED"}
    assert set(children["tags.mlflow.parentRunId"]) == set(parents["run_id"])
    settings = sorted(zip(children["params.model.name"], children["params.seed"], strict=True))
    assert settings == sorted((m, s) for m in ("cross_bilateral", "oidn") for s in "012")
    for key in ("metrics.eval_psnr", "metrics.eval_relmse", "metrics.eval_ssim"):
        assert children[key].notna().all(), key


def test_lr_search_smoke_runs_optuna_trials_and_reports_each(smoke_data, tmp_path):
    out = sweep(["+sweep=lr_search", "hydra.sweeper.n_trials=2"], smoke_data, tmp_path)
    trials = read_csv(tmp_path / "sweep" / "optuna_trials.csv")
    assert len(trials) == 2 and {t["state"] for t in trials} == {"COMPLETE"}
    best = OmegaConf.load(tmp_path / "sweep" / "optuna_best.yaml")
    assert best.value == min(float(t["value"]) for t in trials) and "optuna: best" in out
    rows = method_rows(tmp_path / "reports" / "sweeps" / "lr_search" / "comparison.csv")
    assert len(rows) == 2 and {"lr", "batch_size"} <= {k.rsplit(".", 1)[-1] for k in rows[0]}


def test_a_users_own_denoiser_runs_beside_a_builtin_one(smoke_data, tmp_path):
    """docs/extending.md: one module (tests/plugins/toy_denoiser.py) and one YAML each
    (tests/conf/model/toy.yaml, a two-branch model; toy_color.yaml, one branch predicting colour;
    toy_filter.yaml, a filter) outside src/ are trained (the learned ones), evaluated and reported beside
    DPCN by one multirun."""
    models = "model=dpcn,toy,toy_color,toy_filter"  # toy_filter: a non-learned filter, evaluated only
    sweep([models, "hydra.searchpath=[file://tests/conf]"], smoke_data, tmp_path)
    table = pd.read_csv(tmp_path / "reports" / "denoise" / "comparison.csv", comment="#", index_col=0)
    assert sorted(table.index) == ["dpcn", "noisy input", "toy", "toy_color", "toy_filter"]
    table = table.drop(index="noisy input")
    assert (table["PSNR"] > 0).all() and (table["runs"] == 1).all()
    checkpoints = [load_checkpoint(p) for p in (tmp_path / "sweep").glob("*/checkpoints/final.pt")]
    by_name = {c["model_config"]["name"]: c for c in checkpoints}
    assert set(by_name) == {"dpcn", "toy", "toy_color"}
    # the colour model is fitted on colour alone: its curves hold the colour loss and no branch losses
    color_curves = by_name["toy_color"]["curves"]
    assert color_curves and {"train_loss_color", "val_loss_color"} <= set(color_curves[-1])
    assert not any("diffuse" in key for key in color_curves[-1])
    assert set(by_name["toy_color"]["model"]) == {f"net.{i}.{w}" for i in (0, 2) for w in ("weight", "bias")}
    toy = by_name["toy"]
    assert toy["step"] > 0
    assert toy["model_config"]["_target_"] == "tests.plugins.toy_denoiser.ToyDenoiser"
    assert set(toy["model"]) == {
        f"nets.{b}.{i}.{w}" for b in ("diffuse", "specular") for i in (0, 2) for w in ("weight", "bias")
    }


def test_a_users_own_radiance_field_runs_beside_nerf(smoke_data, tmp_path):
    """The same for a radiance field: tests/plugins/toy_field.py (a `NerfModelBase` subclass) and
    tests/conf/model/toy_field.yaml, trained, evaluated and reported beside NeRF on one scene."""
    args = [
        "task=nerf",
        "task.scene=spheres",
        "model=nerf,toy_field",
        "hydra.searchpath=[file://tests/conf]",
    ]
    sweep(args, smoke_data, tmp_path)
    table = pd.read_csv(tmp_path / "reports" / "nerf" / "comparison.csv", comment="#", index_col=0)
    assert sorted(table.index) == ["nerf", "toy_field"]
    psnr = [c for c in table.columns if "PSNR" in c and "std" not in c]
    assert psnr and (table[psnr] > 0).all().all()
    toy = next(
        c
        for p in (tmp_path / "sweep").glob("*/checkpoints/final.pt")
        if (c := load_checkpoint(p))["model_config"]["name"] == "toy_field"
    )
    assert toy["model_config"]["_target_"] == "tests.plugins.toy_field.ToyField" and toy["step"] > 0
    assert set(toy["model"]) == {"mlps.0.0.weight", "mlps.0.0.bias", "mlps.0.2.weight", "mlps.0.2.bias"}


def _leaves(loop):
    """A foreach's list (or variable), or each of a matrix's lists (or variables)."""
    return list(loop.values()) if isinstance(loop, dict) else [loop]


def _is_variable(value) -> bool:
    return isinstance(value, str) and value.startswith("${") and value.endswith("}")


def test_the_compared_models_live_in_one_place():
    """conf/compare.yaml is what the denoisers / nerf_variants sweeps and the DVC pipeline compare."""
    from dvc.repo import Repo

    compare = compose_sweep("denoisers").compare
    denoisers, nerf = swept(compose_sweep("denoisers")), swept(compose_sweep("nerf_variants"))
    learned, baselines = list(compare.denoise.learned), list(compare.denoise.baselines)
    assert list(denoisers["model"].sweep_string_iterator()) == learned + baselines
    assert list(nerf["model"].sweep_string_iterator()) == list(compare.nerf.models)
    assert values(nerf["task.scene"]) == list(compare.nerf.scenes)
    stages = {s.addressing for s in Repo(ROOT).index.stages}

    def items(kind):
        return {s.split("@", 1)[1] for s in stages if s.startswith(f"{kind}@")}

    assert items("denoise_config") == set(learned) and items("denoise_baseline_config") == set(baselines)
    assert items("denoise_train") == items("denoise_eval") == set(learned)
    assert items("denoise_baseline") == set(baselines)
    assert items("nerf_train") == {f"{m}-{s}" for m in compare.nerf.models for s in compare.nerf.scenes}
    vol_learned, vol_baselines = list(compare.volumetric.learned), list(compare.volumetric.baselines)
    unet_vs_kpcn = swept(compose_sweep("unet_vs_kpcn"))
    assert list(unet_vs_kpcn["model"].sweep_string_iterator()) == vol_learned + vol_baselines
    assert items("vol_config") == set(vol_learned) and items("vol_baseline_config") == set(vol_baselines)
    assert items("vol_train") == items("vol_eval") == set(vol_learned)
    assert items("vol_baseline") == set(vol_baselines)
    # ... and not by coincidence: every list dvc.yaml loops over is a template variable (from
    # conf/compare.yaml), none written out by hand.
    raw = yaml.safe_load((ROOT / "dvc.yaml").read_text())["stages"]
    loops = {n: s.get("foreach", s.get("matrix")) for n, s in raw.items() if "foreach" in s or "matrix" in s}
    written = {n: v for n, v in loops.items() if not all(_is_variable(x) for x in _leaves(v))}
    assert not written, f"dvc.yaml stages loop over lists written out by hand: {written}"


def test_the_volumetric_studies_sweep_what_they_name():
    """feature_selection: four arms (all, selected k, colour only, k random); temporal_loss: lambda 0 and
    the default; both on the U-Net KPCN and the volumetric sequences, in their own MLflow experiment."""
    selection, temporal = compose_sweep("feature_selection"), compose_sweep("temporal_loss")
    arms = swept(selection)["+selection_arm"]
    assert list(arms.sweep_string_iterator()) == ["all", "selected", "color_only", "random"]
    weights = list(swept(temporal)["dataset.train.temporal_weight"].sweep_string_iterator())
    assert weights[0] == "0.0" and float(weights[1]) == temporal.dataset.train.temporal_weight > 0
    assert list(temporal.report.metrics)[:3] == ["Flicker vs truth", "Flicker", "tPSNR"]  # the claim's
    for cfg in (selection, temporal):
        assert cfg.dataset.name == "volumetric" and cfg.model.name == "unet_kpcn"
        assert cfg.tracking.experiment == "nrbench-denoise-volumetric"
    k = selection.compare.volumetric.selected_size
    for arm, (size, order) in {
        "selected": (k, "greedy"),
        "color_only": (0, "greedy"),
        "random": (k, "random"),
    }.items():
        arm_cfg = compose_config(["+sweep=feature_selection", f"+selection_arm={arm}"])
        assert (arm_cfg.dataset.feature_selection.size, arm_cfg.dataset.feature_selection.order) == (
            size,
            order,
        )


@pytest.mark.slow
def test_the_nerf_thesis_sweep_writes_the_thesis_tables(tmp_path, mitsuba_variant):
    """`+sweep=nerf_thesis` on Blender-format scenes named as nerf_synthetic's: one quality table per scene
    (PSNR, LPIPS, SSIM: the thesis's Tables 6.1-6.5) and the cost table (its Table 6.6). Smoke-sized:
    two procedural scenes stand in for lego and materials, two models."""
    from src.stages import render

    rendered = tmp_path / "rendered"
    render(smoke_config(rendered, rendered / "run", ["task=nerf"]))
    root = tmp_path / "nerf_synthetic"
    for ours, theirs in (("spheres", "lego"), ("busy", "materials")):
        shutil.copytree(rendered / "nerf_procedural" / "smoke" / "scenes" / ours, root / theirs)
    sweep(["+sweep=nerf_thesis", f"dataset.root={root}", "task.scene=lego,materials", "model=nerf,mipnerf"],
          tmp_path / "data", tmp_path)  # fmt: skip
    out = tmp_path / "reports" / "sweeps" / "nerf_thesis"
    for scene in ("lego", "materials"):
        table = pd.read_csv(out / f"comparison_{scene}.csv", comment="#", index_col=0)
        assert list(table.index) == ["nerf", "mipnerf"]
        columns = [c for c in table.columns if not c.endswith(" std") and c != "runs"]
        assert columns[0] == "PSNR" and columns[1].startswith("LPIPS") and columns[2] == "SSIM"
        assert len(columns) == 3 and (table["PSNR"] > 0).all()
    cost = pd.read_csv(out / "cost.csv", comment="#", index_col=0)
    assert (
        (cost["iterations"] == 30).all() and (cost["params"] > 0).all() and (cost["train time (s)"] > 0).all()
    )


@pytest.mark.slow
def test_the_gp_expansion_sweep_reports_each_setting(smoke_data, tmp_path):
    """`+sweep=gp_expansion` at the smoke profile, two seeds: one row per Table 4.2 setting with the best
    fitness and the held-out relMSE / PSNR (no confounding warning: the per-job search dir and the
    search seed do not count), the search curves and the feature usage of the best expressions."""
    sweep(["+sweep=gp_expansion", "seed=0,1"], smoke_data, tmp_path)
    out = tmp_path / "reports" / "sweeps" / "gp_expansion"
    rows = method_rows(out / "comparison.csv")
    assert {tuple(float(r[f"task.search.{k}"]) for k in EXPANSION) for r in rows} == set(TABLE_4_2)
    for r in rows:
        assert 0 < float(r["min fitness"]) <= float(r["best fitness"]), r
        assert float(r["PSNR"]) > 0 and float(r["relMSE / noisy"]) > 0, r
        assert r["runs"] == "2"
    assert "Warning" not in (out / "comparison.md").read_text()
    usage = read_csv(out / "feature_usage.csv")
    assert usage and all(int(u["runs"]) >= 1 and float(u["occurrences"]) >= 1 for u in usage)
    assert (out / "search_curves.png").is_file() and (out / "feature_usage.md").is_file()
    # quality against time: the search's minimum fitness against its clock, per arm
    timed = read_table(out / "quality_vs_time.csv")
    assert len(timed) == len(rows) and all(r["runs"] == "2" for r in timed)
    for r in rows:
        mine = [t for t in timed if all(t[f"task.search.{k}"] == r[f"task.search.{k}"] for k in EXPANSION)]
        assert float(mine[0]["final search fitness (min so far)"]) == pytest.approx(float(r["min fitness"]))
    assert "best fitness per generation" in (out / "index.html").read_text()


@pytest.mark.slow
def test_the_gp_population_sweep_reports_fitness_against_population(smoke_data, tmp_path):
    """`+sweep=gp_population` at the smoke profile, one seed: Figure 4.7 as a table (one row per
    population, 2-16 per island at smoke), Figure 4.6 as the search curves, Figure 4.8 as the feature
    usage of the runs' best expressions."""
    sweep(["+sweep=gp_population", "seed=0"], smoke_data, tmp_path)
    out = tmp_path / "reports" / "sweeps" / "gp_population"
    rows = method_rows(out / "comparison.csv")
    assert sorted(int(float(r["task.search.population"])) for r in rows) == [2, 4, 8, 16]
    for r in rows:
        assert 0 < float(r["min fitness"]) <= float(r["best fitness"]), r
        assert float(r["PSNR"]) > 0 and r["runs"] == "1", r
    assert "Warning" not in (out / "comparison.md").read_text()
    assert read_csv(out / "feature_usage.csv") and (out / "search_curves.png").is_file()
