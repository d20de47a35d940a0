"""`python -m src.studies`: a study's jobs as Hydra's sweeper makes them, the done ones found in the tracking
store by the digest the jobs themselves tag their runs with, a dry run listing them, and a launch whose
rerun runs only the jobs not done."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from mlflow.tracking import MlflowClient

from src.studies.plan import expand, ledger_studies, study_jobs
from src.tracking.finished import DIGEST_TAG
from tests.conftest import ROOT


def test_a_studys_jobs_are_the_products_hydras_basic_sweeper_makes():
    """Against Hydra's own expansion (its basic sweeper's `split_arguments`), with a list, a range, a
    fixed value and a `+` key."""
    from hydra._internal.core_plugins.basic_sweeper import BasicSweeper
    from hydra.core.override_parser.overrides_parser import OverridesParser

    params = {"model": "kpcn,dpcn", "seed": "range(3)", "profile": "smoke", "+selection_arm": "all,random"}
    parsed = OverridesParser.create().parse_overrides([f"{k}={v}" for k, v in params.items()])
    (hydras,) = BasicSweeper.split_arguments(parsed, None)
    ours = expand(params)
    assert len(ours) == 12 and sorted(map(sorted, ours)) == sorted(map(sorted, hydras))
    assert expand({"seed": "0"}) == [("seed=0",)]


def test_the_ledgers_studies_are_those_of_the_claims_meaningful_at_the_profile():
    """Against the claims file read as plain YAML: every `runs.study` of a claim listing the profile."""
    import yaml

    raw = yaml.safe_load((ROOT / "conf" / "claims.yaml").read_text())["claims"]
    for profile in ("cpu", "paper", "thesis", "smoke"):
        expected = [c["runs"]["study"] for c in raw if profile in c["profiles"] and "study" in c["runs"]]
        studies = ledger_studies(ROOT / "conf" / "claims.yaml", profile)
        assert studies == list(dict.fromkeys(expected)), profile  # first appearance, once each


TINY = """# @package _global_
hydra:
  sweep:
    dir: {sweeps}/tiny/${{now:%H-%M-%S-%f}}
  sweeper:
    params:
      model: cross_bilateral
      seed: {seeds}
report:
  name: sweeps/tiny
"""


def _studies(args, tmp_path, searchpath):
    env = {
        **os.environ,
        "NRBENCH_DATA_DIR": str(tmp_path / "data"),
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path}/mlflow.db",
    }
    command = [
        sys.executable, "-m", "src.studies", "--profile", "smoke", *args, f"hydra.searchpath=[file://{searchpath}]",
        "metrics.lpips.enabled=false", "metrics.flip.enabled=false", "report.site=false",
        f"tracking.artifact_root={tmp_path}/mlartifacts", f"report.out_dir={tmp_path}/reports",
        f"ledger.out_dir={tmp_path}/reports",
    ]  # fmt: skip
    ran = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    return ran.returncode, ran.stdout + ran.stderr


def _job_runs(tmp_path):
    client = MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")
    runs = [r for e in client.search_experiments() for r in client.search_runs([e.experiment_id])]
    return [r for r in runs if r.data.tags.get("nrbench.sweep_parent") != "true"]


def _tiny_studies(tmp_path):
    """`<tmp>/conf/sweep/{tiny,tiny3}.yaml`: cross-bilateral at seeds 0,1 and 0,1,2; the search path."""
    searchpath = tmp_path / "conf"
    (searchpath / "sweep").mkdir(parents=True)
    for name, seeds in (("tiny", "0,1"), ("tiny3", "0,1,2")):
        (searchpath / "sweep" / f"{name}.yaml").write_text(
            TINY.format(sweeps=tmp_path / "sweeps", seeds=seeds)
        )
    return searchpath


@pytest.mark.slow  # 22 s; its SLURM twin (tests/test_cluster.py, also slow) launches the same study
def test_a_study_launches_its_data_once_then_its_jobs_tagged_with_the_planned_digests(tmp_path):
    searchpath = _tiny_studies(tmp_path)
    code, out = _studies(["--study", "tiny"], tmp_path, searchpath)
    assert code == 0, out[-3000:]
    assert "study tiny: 2 jobs, 0 done, 2 to run (1 data job first); time left unknown" in out
    assert "1 studies at profile smoke: 2 jobs to run, time left unknown (no study has a done job)" in out
    launched = [line for line in out.splitlines() if line.startswith("+ ")]
    assert len(launched) == 2 and "task.stages=[render,preprocess]" in launched[0]  # the data once, first
    assert "skip_finished=true" in launched[1]
    runs = _job_runs(tmp_path)
    assert len(runs) == 2 and {r.info.status for r in runs} == {"FINISHED"}
    # The digest each job computed in its own Hydra run is the one the plan computes for it.
    planned = {
        job.overrides: job.digest
        for job in study_jobs("tiny", "smoke", [f"hydra.searchpath=[file://{searchpath}]",
                                                "metrics.lpips.enabled=false", "metrics.flip.enabled=false",
                                                "report.site=false"])
    }  # fmt: skip
    logged = {
        ("model=cross_bilateral", f"seed={r.data.params['seed']}"): r.data.tags[DIGEST_TAG] for r in runs
    }
    assert logged == planned and len(set(planned.values())) == 2
    # The same study with a third seed: the two are done (their durations give the estimate).
    code, out = _studies(["--study", "tiny3", "--dry-run"], tmp_path, searchpath)
    assert code == 0, out[-3000:]
    assert "study tiny3: 3 jobs, 2 done, 1 to run (1 data job first); time left" in out
    assert "time left unknown" not in out
    assert re.search(r"1 studies at profile smoke: 1 jobs to run, time left \d+ s of jobs \(run one", out)
    assert out.count("done    run ") == 2 and "seed=2  ~" in out
    assert not (tmp_path / "sweeps" / "tiny3").exists()  # a dry run runs nothing


@pytest.mark.slow
def test_a_rerun_of_a_grown_study_runs_only_the_jobs_not_done(tmp_path):
    searchpath = _tiny_studies(tmp_path)
    code, out = _studies(["--study", "tiny"], tmp_path, searchpath)
    assert code == 0, out[-3000:]
    code, out = _studies(["--study", "tiny3"], tmp_path, searchpath)
    assert code == 0, out[-3000:]
    launched = [line for line in out.splitlines() if line.startswith("+ ")]
    assert len(launched) == 2 and "seed=2 task.stages=[render,preprocess]" in launched[0]
    assert "render: all 9 files up to date" in out  # the data job finds the data there
    assert out.count("skipped: this configuration already has a FINISHED run") == 2
    runs = _job_runs(tmp_path)
    assert sorted(r.data.params["seed"] for r in runs) == ["0", "1", "2"]  # only seed 2 ran


def test_an_unknown_study_is_one_line_and_exit_2(tmp_path):
    code, out = _studies(["--study", "no_such_study", "--dry-run"], tmp_path, tmp_path)
    assert code == 2 and "Traceback" not in out
    (line,) = [line for line in out.splitlines() if line.startswith("error:")]
    assert "no_such_study" in line


def _tagged_run(uri: str, experiment: str, digest: str, status: str) -> str:
    client = MlflowClient(uri)
    found = client.get_experiment_by_name(experiment)
    experiment_id = found.experiment_id if found else client.create_experiment(experiment)
    run = client.create_run(experiment_id, tags={DIGEST_TAG: digest})
    client.set_terminated(run.info.run_id, status)
    return run.info.run_id


def test_only_a_finished_run_makes_a_configuration_done(tmp_path):
    from src.tracking.finished import finished_runs

    uri = f"sqlite:///{tmp_path}/mlflow.db"
    assert finished_runs(uri, "nrbench-denoise") == {}  # no such experiment yet
    killed = _tagged_run(uri, "nrbench-denoise", "aaaa", "KILLED")
    failed = _tagged_run(uri, "nrbench-denoise", "bbbb", "FAILED")
    done = _tagged_run(uri, "nrbench-denoise", "cccc", "FINISHED")
    _tagged_run(uri, "other", "dddd", "FINISHED")
    found = finished_runs(uri, "nrbench-denoise")
    assert set(found) == {"cccc"} and found["cccc"].run_id == done
    assert killed not in {r.run_id for r in found.values()} and failed != done


def test_a_whole_job_of_a_done_configuration_is_skipped_only_with_skip_finished(tmp_path):
    from src.provenance import config_digest
    from src.run import _finished_already
    from tests.conftest import smoke_config

    def cfg(*extra):
        return smoke_config(tmp_path, tmp_path / "run", ["model=cross_bilateral", *extra])

    uri, experiment = str(cfg().tracking.uri), str(cfg().tracking.experiment)
    stages = ["render", "preprocess", "eval"]
    assert _finished_already(cfg("skip_finished=true"), stages) is None  # nothing done yet
    _tagged_run(uri, experiment, config_digest(cfg("seed=1")), "FINISHED")
    assert _finished_already(cfg("skip_finished=true"), stages) is None  # another seed is done
    done = _tagged_run(uri, experiment, config_digest(cfg()), "FINISHED")
    assert _finished_already(cfg("skip_finished=true"), stages) == done
    assert _finished_already(cfg(), stages) is None  # skip_finished=false (the default): run it again
    assert _finished_already(cfg("skip_finished=true", "stage=eval"), ["eval"]) is None  # not a whole job


def test_a_jobs_estimate_is_its_models_median_else_its_studys_else_unknown():
    from src.studies.plan import StudyJob, estimate_seconds
    from src.tracking.finished import FinishedRun

    def job(model, seed):
        return StudyJob("s", (f"model={model}", f"seed={seed}"), f"{model}{seed}", "d", (), model, "u", "e")

    jobs = [job("kpcn", s) for s in range(4)] + [job("dpcn", s) for s in range(2)] + [job("oidn", 0)]
    done = {
        "kpcn0": FinishedRun("r0", 100.0, "kpcn"),
        "kpcn1": FinishedRun("r1", 300.0, "kpcn"),
        "kpcn2": FinishedRun("r2", 200.0, "kpcn"),
        "dpcn0": FinishedRun("r3", 1000.0, "dpcn"),
    }
    assert estimate_seconds(jobs[3], done, jobs) == 200.0  # kpcn: median of 100, 300, 200
    assert estimate_seconds(jobs[5], done, jobs) == 1000.0  # dpcn: its one done job
    assert estimate_seconds(jobs[6], done, jobs) == 250.0  # oidn: none done, the study's median
    assert estimate_seconds(jobs[6], {}, jobs) is None


def test_jobs_share_their_data_unless_a_data_key_differs():
    """Seeds and models share the data; a data seed, a dataset size or the preprocessing do not."""
    from src.studies.plan import data_identity
    from tests.conftest import compose_config

    def identity(*overrides):
        return data_identity(compose_config(["profile=smoke", "paths.run_dir=/x", *overrides]))

    same = identity("model=kpcn", "seed=0")
    assert identity("model=dpcn", "seed=3") == same and identity("task.train.lr=0.01") == same
    for other in (
        "data_seed=1",
        "dataset.noisy_spp=[4,8]",
        "task.preprocess.patch_size=16",
        "task=filter_search",
    ):
        assert identity(other) != same, other
