"""MLflow run lifecycle: job runs, resume, failure statuses, comparison tables and the sweep callback."""

import json
import math
import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import mlflow
import pytest
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from src.errors import ConfigError
from src.multirun import PARENT_FILE
from src.tracking import mlflow_tracking as mt
from src.tracking.comparison import DEFAULT_COLUMNS, comparison_table, format_table
from src.tracking.experiment import run_url_line, setup_tracking
from src.tracking.mlflow_tracking import job_run
from src.tracking.run_config import TRUNCATED, flatten_config
from tests.conftest import one_line_error

ROOT = Path(__file__).resolve().parent.parent


def make_cfg(tmp_path, enabled=True, **extra):
    """A job config with tracking into `tmp_path` (SQLite + local artifacts)."""
    tracking = {
        "enabled": enabled,
        "uri": f"sqlite:///{tmp_path}/mlflow.db",
        "artifact_root": str(tmp_path / "mlartifacts"),
        "experiment": "nrbench-test",
    }
    return OmegaConf.create({"tracking": tracking, "model": {"name": "kpcn", "widths": [8, 16]}, **extra})


@pytest.fixture(scope="session")
def empty_db(tmp_path_factory):
    """An MLflow SQLite database with its schema created once: creating one runs ~40 migrations (s)."""
    path = tmp_path_factory.mktemp("mlflow-template") / "mlflow.db"
    MlflowClient(f"sqlite:///{path}").search_experiments()
    return path


@pytest.fixture
def store(tmp_path, empty_db):
    """`tmp_path` holding a fresh copy of the empty database (what `make_cfg` points tracking at)."""
    shutil.copy(empty_db, tmp_path / "mlflow.db")
    return tmp_path


@pytest.fixture(autouse=True)
def _no_leaked_run():
    yield
    assert mlflow.active_run() is None
    mlflow.set_tracking_uri(None)


def test_flatten_config_nested_lists_and_truncation():
    cfg = OmegaConf.create(
        {"a": {"b": 1, "c": [1, 2, {"d": "x"}]}, "e": None, "ref": "${a.b}", "long": "y" * 7000, "f": {}}
    )
    flat = flatten_config(cfg)
    assert flat["a.b"] == "1" and flat["ref"] == "1" and flat["e"] == "None" and flat["f"] == "{}"
    assert json.loads(flat["a.c"]) == [1, 2, {"d": "x"}]
    assert len(flat["long"]) == 6000 and flat["long"].endswith(TRUNCATED)
    assert all(isinstance(v, str) for v in flat.values())
    assert flatten_config({"x": {"y": 2}}, sep="/") == {"x/y": "2"}


def test_flatten_config_keeps_unresolvable_interpolations_as_text():
    flat = flatten_config(OmegaConf.create({"run_dir": "${hydra:runtime.output_dir}", "n": 3}))
    assert flat == {"run_dir": "${hydra:runtime.output_dir}", "n": "3"}


def test_job_run_logs_params_tags_metrics_and_config(store):
    cfg = make_cfg(store, notes="z" * 7000)
    with job_run(cfg, run_name="kpcn-smoke", tags={"nrbench.model": "kpcn"}) as tracker:
        tracker.log_metrics({"loss": 1.0, "lr": 0.1}, step=0)
        tracker.log_metric("loss", 0.5, step=1)
        tracker.log_dict({"psnr": 30.0}, "eval/metrics.json")
        tracker.set_tags({"stage": "train"})
        assert mlflow.active_run().info.run_id == tracker.run_id  # library code can use mlflow.log_*
    run = mlflow.get_run(tracker.run_id)
    assert run.info.status == "FINISHED" and run.info.run_name == "kpcn-smoke"
    assert run.data.params["model.name"] == "kpcn" and run.data.params["model.widths"] == "[8, 16]"
    assert len(run.data.params["notes"]) == 6000
    tags = run.data.tags
    assert tags["nrbench.model"] == "kpcn" and tags["stage"] == "train"
    assert tags["nrbench.git_dirty"] in ("true", "false") and "+" not in tags["nrbench.git_commit"]
    assert "mlflow.parentRunId" not in tags and "nrbench.sweep_dir" not in tags
    history = MlflowClient().get_metric_history(tracker.run_id, "loss")
    assert [(m.step, m.value) for m in history] == [(0, 1.0), (1, 0.5)]
    artifacts = {f.path for f in MlflowClient().list_artifacts(tracker.run_id)}
    assert {"config.yaml", "eval"} <= artifacts
    assert run.info.artifact_uri.startswith((store / "mlartifacts").as_uri())
    logged = OmegaConf.load(
        mlflow.artifacts.download_artifacts(run_id=tracker.run_id, artifact_path="config.yaml")
    )
    assert logged.model.name == "kpcn" and logged.tracking.experiment == "nrbench-test"


def test_a_job_prints_its_runs_url_which_names_the_store_the_ui_script_must_serve(store, capsys):
    with job_run(make_cfg(store), run_name="kpcn-smoke", tags={}) as tracker:
        pass
    experiment = mlflow.get_run(tracker.run_id).info.experiment_id
    script = f"MLFLOW_TRACKING_URI=sqlite:///{store}/mlflow.db bash scripts/mlflow_ui.sh"
    assert capsys.readouterr().out == (
        f"MLflow run: http://127.0.0.1:5000/#/experiments/{experiment}/runs/{tracker.run_id} "
        f"(once the UI runs: {script})\n"
    )
    # the project's own store is the script's default: no variable to set; a server is its own UI
    assert run_url_line(f"sqlite:///{ROOT}/mlflow.db", "3", "abc") == (
        "MLflow run: http://127.0.0.1:5000/#/experiments/3/runs/abc "
        "(once the UI runs: bash scripts/mlflow_ui.sh)"
    )
    assert run_url_line("http://mlflow.lab:8080/", "3", "abc") == (
        "MLflow run: http://mlflow.lab:8080/#/experiments/3/runs/abc"
    )
    assert run_url_line("databricks", "3", "abc") == "MLflow run abc (experiment 3) in databricks"


def test_a_resumed_run_prints_the_url_in_its_own_experiment(store, capsys):
    with job_run(make_cfg(store), run_name="first", tags={}) as first:
        pass
    other = make_cfg(store)
    other.tracking.experiment = "nrbench-other"
    capsys.readouterr()
    with job_run(other, run_name="again", tags={}, resume_run_id=first.run_id):
        pass
    experiment = mlflow.get_run(first.run_id).info.experiment_id
    assert f"/#/experiments/{experiment}/runs/{first.run_id} " in capsys.readouterr().out
    assert experiment != MlflowClient().get_experiment_by_name("nrbench-other").experiment_id


def test_many_params_are_batched(store):
    cfg = make_cfg(store, wide={f"k{i}": i for i in range(250)})
    with job_run(cfg, run_name="wide", tags={}) as tracker:
        pass
    assert len(mlflow.get_run(tracker.run_id).data.params) == 250 + 4 + 2


def test_exception_marks_run_failed_and_propagates(store):
    with (
        pytest.raises(RuntimeError, match="boom"),
        job_run(make_cfg(store), run_name="x", tags={}) as tracker,
    ):
        raise RuntimeError("boom")
    assert mlflow.get_run(tracker.run_id).info.status == "FAILED"


def test_keyboard_interrupt_marks_run_killed(store):
    with pytest.raises(KeyboardInterrupt), job_run(make_cfg(store), run_name="x", tags={}) as tracker:
        raise KeyboardInterrupt
    assert mlflow.get_run(tracker.run_id).info.status == "KILLED"


def test_resume_continues_the_same_run(store):
    cfg = make_cfg(store)
    with job_run(cfg, run_name="r", tags={}) as first:
        first.log_metric("loss", 1.0, step=0)
    resumed_cfg = make_cfg(store, model={"name": "kpcn", "widths": [8, 32]}, extra_key=5)
    with job_run(resumed_cfg, run_name="r", tags={"resumed": "yes"}, resume_run_id=first.run_id) as second:
        assert second.run_id == first.run_id
        second.log_metric("loss", 0.5, step=1)
    run = mlflow.get_run(first.run_id)
    assert run.info.status == "FINISHED" and run.data.tags["resumed"] == "yes"
    assert run.data.params["model.widths"] == "[8, 16]"  # original value kept, no MLflow error
    assert run.data.params["extra_key"] == "5"  # keys new on resume are added
    history = MlflowClient().get_metric_history(first.run_id, "loss")
    assert [(m.step, m.value) for m in history] == [(0, 1.0), (1, 0.5)]
    assert len(mlflow.search_runs(experiment_names=["nrbench-test"])) == 1


def test_a_resumed_training_does_not_log_the_steps_a_crash_left_logged_again(store):
    """Killed (SIGKILL) at step 5 after a checkpoint at step 3: the resumed job replays steps 4 and 5 and
    logs each step once."""
    with job_run(make_cfg(store), run_name="r", tags={}) as first:
        for step in range(1, 6):
            first.log_metrics({"loss": 1.0 / step, "psnr": float(step)}, step=step)
    with job_run(make_cfg(store), run_name="r", tags={}, resume_run_id=first.run_id) as resumed:
        resumed.skip_logged_after(3)
        for step in range(4, 8):
            resumed.log_metrics({"loss": 1.0 / step, "psnr": float(step)}, step=step)
    for key in ("loss", "psnr"):
        history = MlflowClient().get_metric_history(first.run_id, key)
        assert sorted(m.step for m in history) == list(range(1, 8)), key


def test_resume_of_an_unknown_run_starts_a_new_one(store, caplog):
    with job_run(make_cfg(store), run_name="r", tags={}, resume_run_id="f" * 32) as tracker:
        pass
    assert tracker.run_id != "f" * 32 and mlflow.get_run(tracker.run_id).info.status == "FINISHED"
    assert "starting a new run" in caplog.text


def test_disabled_tracking_is_a_no_op(tmp_path):
    with job_run(make_cfg(tmp_path, enabled=False), run_name="off", tags={}) as tracker:
        tracker.log_metrics({"loss": 1.0}, step=0)
        tracker.log_artifact(__file__)
        tracker.set_tags({"a": "b"})
    assert tracker.run_id is None
    assert not (tmp_path / "mlflow.db").exists()


def test_bad_uri_is_one_line_naming_the_key(tmp_path):
    cfg = make_cfg(tmp_path)
    cfg.tracking.uri = "bogus://nowhere"
    with pytest.raises(ConfigError) as excinfo:
        setup_tracking(cfg.tracking)
    one_line_error(excinfo, "tracking.uri", "bogus://nowhere")


def test_setup_tracking_reuses_an_existing_experiment(store):
    cfg = make_cfg(store)
    assert setup_tracking(cfg.tracking) == setup_tracking(cfg.tracking)


def test_setup_tracking_survives_a_creation_race(store, monkeypatch):
    cfg = make_cfg(store)
    real_get = MlflowClient.get_experiment_by_name
    calls = []

    def stale_get(self, name):  # the first look misses; another process creates it meanwhile
        calls.append(name)
        if len(calls) == 1:
            MlflowClient(cfg.tracking.uri).create_experiment(name)
            return None
        return real_get(self, name)

    monkeypatch.setattr(MlflowClient, "get_experiment_by_name", stale_get)
    experiment_id = setup_tracking(cfg.tracking)
    assert experiment_id == real_get(MlflowClient(cfg.tracking.uri), "nrbench-test").experiment_id


def _fake_sweep(monkeypatch, store):
    """Pretend to be a job of a Hydra multirun in `store/sweep` (the record is the test's business)."""
    sweep = store / "sweep"
    sweep.mkdir()
    monkeypatch.setattr(mt, "_hydra_job", lambda: ("lr=0.1", sweep))
    return sweep


def _sweep_with_parent(monkeypatch, store):
    """(config, sweep dir, parent run) of a job of a fake multirun whose parent run exists and is recorded."""
    cfg = make_cfg(store)
    sweep = _fake_sweep(monkeypatch, store)
    experiment_id = setup_tracking(cfg.tracking)
    parent = MlflowClient().create_run(experiment_id, run_name="sweep")
    record = {"run_id": parent.info.run_id, "experiment_id": experiment_id, "tracking_uri": cfg.tracking.uri}
    (sweep / PARENT_FILE).write_text(json.dumps(record))
    return cfg, sweep, parent


def test_multirun_job_becomes_child_and_failure_marks_parent(store, monkeypatch):
    cfg, sweep, parent = _sweep_with_parent(monkeypatch, store)
    with pytest.raises(ValueError), job_run(cfg, run_name="child", tags={}) as tracker:
        raise ValueError
    tags = mlflow.get_run(tracker.run_id).data.tags
    assert tags["mlflow.parentRunId"] == parent.info.run_id and tags["nrbench.sweep_dir"] == str(sweep)
    assert tags["nrbench.hydra_job"] == "lr=0.1"
    assert mlflow.get_run(parent.info.run_id).info.status == "FAILED"


@pytest.mark.parametrize("requeued", [True, False])
def test_a_job_exiting_to_be_requeued_leaves_its_sweeps_parent_running(store, monkeypatch, requeued):
    """submitit's exit after a requeue: the child ends KILLED (its restarted job reopens it) and the parent
    stays RUNNING; any other non-zero exit fails both."""
    import sys
    import threading

    from src.launch import requeue

    monkeypatch.setattr(requeue, "REQUEUED", threading.Event())
    cfg, _, parent = _sweep_with_parent(monkeypatch, store)
    with pytest.raises(SystemExit), job_run(cfg, run_name="child", tags={}) as tracker:
        if requeued:
            requeue.mark_requeued()
        sys.exit(-1)
    child, parent_now = (mlflow.get_run(r).info.status for r in (tracker.run_id, parent.info.run_id))
    assert (child, parent_now) == (("KILLED", "RUNNING") if requeued else ("FAILED", "FAILED"))


def test_multirun_without_parent_record_is_top_level(store, monkeypatch, caplog):
    cfg = make_cfg(store)
    _fake_sweep(monkeypatch, store)
    with job_run(cfg, run_name="orphan", tags={}) as tracker:
        pass
    assert "mlflow.parentRunId" not in mlflow.get_run(tracker.run_id).data.tags
    assert "top-level" in caplog.text


def _log_child(parent_id, experiment_id, name, metrics, status="FINISHED"):
    client = MlflowClient()
    tags = {"mlflow.parentRunId": parent_id, "nrbench.model": name}
    run = client.create_run(experiment_id, tags=tags, run_name=name)
    for key, value in metrics.items():
        client.log_metric(run.info.run_id, key, value)
    client.set_terminated(run.info.run_id, status)


def test_comparison_table_children_sorted_by_relmse(store):
    experiment_id = setup_tracking(make_cfg(store).tracking)
    sweep_tag = {"nrbench.sweep_parent": "true"}
    parent = MlflowClient().create_run(experiment_id, tags=sweep_tag, run_name="sweep").info.run_id
    other = MlflowClient().create_run(experiment_id, tags=sweep_tag, run_name="other").info.run_id
    _log_child(parent, experiment_id, "kpcn", {"eval_relmse": 0.02, "eval_psnr": 31.0, "param_count": 1e5})
    _log_child(parent, experiment_id, "dpcn", {"eval_relmse": 0.01, "eval_psnr": 32.5})
    _log_child(parent, experiment_id, "broken", {}, status="FAILED")
    _log_child(other, experiment_id, "elsewhere", {"eval_relmse": 0.001})
    table = comparison_table(parent)
    assert list(table.columns) == list(DEFAULT_COLUMNS)
    assert list(table["model"]) == ["dpcn", "kpcn", "broken"]
    assert table.loc[1, "params"] == 1e5 and math.isnan(table.loc[0, "params"])
    assert table["SSIM"].isna().all() and list(table["status"]) == ["FINISHED", "FINISHED", "FAILED"]
    text = format_table(table)
    assert "32.50" in text and "100,000" in text and "relMSE" in text and len(text.splitlines()) == 4
    by_experiment = comparison_table(experiment="nrbench-test", columns={"model": "tags.nrbench.model"})
    assert sorted(by_experiment["model"]) == ["broken", "dpcn", "elsewhere", "kpcn"]  # no sweep parents
    assert format_table(comparison_table("0" * 32)) == "(no runs)"


APP = """
import hydra
from src.tracking.mlflow_tracking import job_run

@hydra.main(version_base="1.3", config_path=".", config_name="config")
def main(cfg):
    with job_run(cfg, run_name=f"job-{cfg.model}", tags={"nrbench.model": cfg.model}) as tracker:
        relmse = {"a": 0.5, "b": 0.1}[cfg.model]
        tracker.log_metrics({"eval_relmse": relmse, "eval_psnr": 30.0, "param_count": 1234.0})

if __name__ == "__main__":
    main()
"""

APP_CONFIG = """
model: a
paths:
  root: ${hydra:runtime.cwd}
tracking:
  enabled: true
  uri: sqlite:///${paths.root}/mlflow.db
  artifact_root: ${paths.root}/mlartifacts
  experiment: sweep-test
hydra:
  job:
    chdir: true
  callbacks:
    mlflow_sweep:
      _target_: src.tracking.callbacks.MlflowSweepCallback
"""


def test_sweep_callback_end_to_end(store):
    (store / "app.py").write_text(APP)
    (store / "config.yaml").write_text(textwrap.dedent(APP_CONFIG))
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["PYTHONPATH"] = str(ROOT)
    cmd = [sys.executable, "app.py", "-m", "model=a,b", "+x=1", "hydra.sweep.dir=sweep"]
    result = subprocess.run(cmd, cwd=store, env=env, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr

    record = json.loads((store / "sweep" / "mlflow_parent.json").read_text())
    assert record["tracking_uri"] == f"sqlite:///{store}/mlflow.db"
    mlflow.set_tracking_uri(record["tracking_uri"])
    runs = mlflow.search_runs(experiment_names=["sweep-test"])
    assert len(runs) == 3
    parent = mlflow.get_run(record["run_id"])
    assert (
        parent.info.status == "FINISHED" and parent.data.tags["nrbench.sweep_overrides"] == "model=a,b +x=1"
    )
    children = runs[runs["tags.mlflow.parentRunId"] == record["run_id"]]
    assert sorted(children["tags.nrbench.model"]) == ["a", "b"] and set(children["status"]) == {"FINISHED"}
    assert set(children["tags.nrbench.sweep_dir"]) == {str(store / "sweep")}
    artifacts = {f.path for f in MlflowClient().list_artifacts(record["run_id"])}
    assert {"comparison.csv", "comparison.txt"} <= artifacts

    out = result.stdout
    assert "== MLflow sweep" in out and record["run_id"] in out
    table_lines = out[out.index("== MLflow sweep") :].splitlines()[1:4]
    assert "relMSE" in table_lines[0] and "job" in table_lines[0]
    assert "model=b" in table_lines[1] and "model=a" in table_lines[2] and "1,234" in table_lines[1]
    assert "+x=1" not in table_lines[1]  # shared by every job: not what tells the rows apart
