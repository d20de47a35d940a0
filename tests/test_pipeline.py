"""What the DVC pipeline relies on: a machine-independent per-model params file, and evaluation of a
trained checkpoint logging into the MLflow run that trained it."""

from src.provenance import result_config
from src.run import _run_to_continue
from src.stages import train
from src.tracking.mlflow_tracking import job_run
from tests.conftest import smoke_config


def test_result_config_leaves_out_paths_and_tracking_only(tmp_path):
    a = result_config(smoke_config(tmp_path / "a", tmp_path / "run-a", ["model=kpcn"]))
    b = result_config(smoke_config(tmp_path / "b", tmp_path / "run-b", ["model=kpcn"]))
    assert a == b  # other data dir, run dir and MLflow store: the same params file
    assert {"paths", "tracking", "report", "stage"}.isdisjoint(a)
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
    assert _run_to_continue(cfg, ["train", "eval"]) is None  # a fresh training starts a new run
    baseline = smoke_config(smoke_data, tmp_path, ["model=oidn"])
    assert _run_to_continue(baseline, ["eval"]) is None
