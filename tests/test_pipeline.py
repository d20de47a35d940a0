"""What the DVC pipeline relies on: a machine-independent per-model params file, and evaluation of a
trained checkpoint logging into the MLflow run that trained it."""

import shutil

import pytest
from mlflow.tracking import MlflowClient

from src.provenance import result_config
from src.run import _run_to_continue, _tracked_run
from src.stages import train
from src.tracking.mlflow_tracking import job_run
from src.train.trainer import train_denoiser
from tests.conftest import data_kind, smoke_config, stop_at


def test_result_config_leaves_out_paths_and_tracking_only(tmp_path):
    a = result_config(smoke_config(tmp_path / "a", tmp_path / "run-a", ["model=kpcn"]))
    b = result_config(smoke_config(tmp_path / "b", tmp_path / "run-b", ["model=kpcn"]))
    assert a == b  # other data dir, run dir and MLflow store: the same params file
    assert {"paths", "tracking", "report", "stage", "compare"}.isdisjoint(a)
    assert "checkpoint_dir" not in a["task"]["train"] and "out_dir" not in a["task"]["eval"]
    assert a["seed"] == 0 and a["model"]["name"] == "kpcn" and a["task"]["train"]["lr"] == 1e-4
    other = result_config(smoke_config(tmp_path / "a", tmp_path / "run-a", ["model=kpcn", "seed=3"]))
    assert other != a


def test_eval_of_a_trained_checkpoint_continues_its_training_run(smoke_data, tmp_path):
    cfg = smoke_config(smoke_data, tmp_path, ["model=resnet", "task.train.max_steps=2"])
    with job_run(cfg, run_name="t", tags={}) as tracker:
        train(cfg, tracker)
        trained_in = tracker.run_id
    assert _run_to_continue(cfg, ["eval"]) == trained_in
    # A training started again in its folder continues its own checkpoint's run (`auto_resume`); with
    # auto_resume=false, or from another folder, it starts a new run.
    assert _run_to_continue(cfg, ["train", "eval"]) == trained_in
    off = smoke_config(smoke_data, tmp_path, ["model=resnet", "task.train.max_steps=2", "auto_resume=false"])
    assert _run_to_continue(off, ["train", "eval"]) is None
    elsewhere = smoke_config(smoke_data, tmp_path / "other", ["model=resnet", "task.train.max_steps=2"])
    assert _run_to_continue(elsewhere, ["train", "eval"]) is None
    baseline = smoke_config(smoke_data, tmp_path, ["model=oidn"])
    assert _run_to_continue(baseline, ["eval"]) is None


def test_resumed_training_continues_its_checkpoints_run(smoke_data, tmp_path, caplog):
    common = ["model=resnet", "task.train.epochs=2"]
    first_cfg = smoke_config(smoke_data, tmp_path / "a", common)
    with _tracked_run(first_cfg, ["train"]) as tracker, pytest.raises(KeyboardInterrupt):
        train_denoiser(first_cfg, tracker, data_kind(first_cfg), on_step=stop_at(3))
    first = tracker.run_id
    # Keep a copy of the interrupted checkpoint for the stale-run case below.
    shutil.copytree(tmp_path / "a" / "checkpoints", tmp_path / "copy")

    resumed_cfg = smoke_config(
        smoke_data, tmp_path / "a", [*common, f"task.train.resume={tmp_path}/a/checkpoints"]
    )
    assert _run_to_continue(resumed_cfg, ["train", "eval"]) == first
    with _tracked_run(resumed_cfg, ["train"]) as tracker:
        summary = train_denoiser(resumed_cfg, tracker, data_kind(resumed_cfg))
    assert tracker.run_id == first
    client = MlflowClient()
    run = client.get_run(first)
    assert run.info.status == "FINISHED" and run.data.tags["nrbench.precision"] == "fp32"
    # One run holds the whole training: per-step losses from before and after the interrupt, once each.
    steps = [m.step for m in client.get_metric_history(first, "train_step_loss_diffuse")]
    assert steps == list(range(1, summary["steps"] + 1))
    assert [m.step for m in client.get_metric_history(first, "epoch")] == [
        summary["steps"] // 2,
        summary["steps"],
    ]

    # The checkpoint's run was deleted since: training goes on, into a new run, with a warning.
    client.delete_run(first)
    stale_cfg = smoke_config(smoke_data, tmp_path / "b", [*common, f"task.train.resume={tmp_path}/copy"])
    assert _run_to_continue(stale_cfg, ["train"]) == first
    with _tracked_run(stale_cfg, ["train"]) as tracker:
        train_denoiser(stale_cfg, tracker, data_kind(stale_cfg))
    assert tracker.run_id != first
    assert client.get_run(tracker.run_id).info.status == "FINISHED"
    assert f"MLflow run {first} (to resume) is not in" in caplog.text


def test_the_task_object_comes_from_config_and_a_bad_one_is_one_line(tmp_path):
    from src.errors import ConfigError
    from src.stages import render, task_of
    from src.tasks.denoise import DenoiseTask
    from src.tasks.nerf import NerfTask
    from tests.conftest import one_line_error

    assert isinstance(task_of(smoke_config(tmp_path, tmp_path / "run")), DenoiseTask)
    assert isinstance(task_of(smoke_config(tmp_path, tmp_path / "run", ["task=nerf"])), NerfTask)
    bad = smoke_config(tmp_path, tmp_path / "run", ["task._target_=src.tasks.nope.Task"])
    with pytest.raises(ConfigError) as excinfo:
        render(bad)
    one_line_error(excinfo, "task._target_", "src.tasks.nope.Task")
