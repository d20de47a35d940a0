"""A job that exits to be requeued (submitit's handler on SLURM's time-out or preemption signal) and starts
again in its run folder: the training continues its newest checkpoint there, in the same MLflow run, to
the weights of an uninterrupted run; a checkpoint another configuration wrote is not continued. The real
scheduler's version of this is in tests/test_cluster.py."""

from __future__ import annotations

import sys
import threading

import pytest
import torch
from mlflow.tracking import MlflowClient

from hydra_plugins.nrbench_slurm_launcher.slurm_launcher import RequeueingSlurmLauncher
from src.launch import requeue
from src.launch.requeue import requeue_pending
from src.provenance import config_digest
from src.run import _run_to_continue, _tracked_run
from src.train.checkpoint import load_checkpoint, resumable_checkpoint, save_checkpoint
from src.train.trainer import train_denoiser
from tests.conftest import data_kind, smoke_config

COMMON = ["model=resnet", "task.train.epochs=3"]


@pytest.fixture
def fresh_flag(monkeypatch):
    """Each test's own requeue flag (a real job exits once it is set; a test process goes on)."""
    monkeypatch.setattr(requeue, "REQUEUED", threading.Event())


def _exit_for_requeue_at(step):
    """What submitit's handler does when the signal arrives during `step`: call the launcher's
    `checkpoint`, requeue, `sys.exit(-1)`."""
    launcher = RequeueingSlurmLauncher()

    def on_step(current):
        if current == step:
            delayed = launcher.checkpoint("overrides", "hydra.sweep.dir", 0, "job", {})
            assert delayed.function is launcher and delayed.args[2] == 0  # resubmits the same job
            sys.exit(-1)

    return on_step


def test_a_requeued_training_continues_in_its_folder_to_the_same_weights_in_one_run(
    smoke_data, tmp_path, fresh_flag
):
    straight = smoke_config(smoke_data, tmp_path / "straight", COMMON)
    with _tracked_run(straight, ["train"]) as tracker:
        reference = train_denoiser(straight, tracker, data_kind(straight))
    steps = reference["steps"]

    cfg = smoke_config(smoke_data, tmp_path / "job", COMMON)
    assert resumable_checkpoint(cfg) is None and _run_to_continue(cfg, ["train", "eval"]) is None
    assert not requeue_pending()
    inside_epoch_2 = steps // 3 + 1
    with pytest.raises(SystemExit), _tracked_run(cfg, ["train"]) as tracker:
        train_denoiser(cfg, tracker, data_kind(cfg), on_step=_exit_for_requeue_at(inside_epoch_2))
    first = tracker.run_id
    assert requeue_pending()
    client = MlflowClient(cfg.tracking.uri)
    assert client.get_run(first).info.status == "KILLED"  # not FAILED: the job comes back
    last = tmp_path / "job" / "checkpoints" / "last.pt"
    saved = load_checkpoint(last)  # written on the way out, mid-epoch
    assert (saved["epoch"], saved["batch_in_epoch"], saved["step"]) == (1, 1, inside_epoch_2)
    assert saved["config_digest"] == config_digest(cfg) and saved["mlflow_run_id"] == first

    # The job starts again: the same config in the same folder, no resume given.
    again = smoke_config(smoke_data, tmp_path / "job", COMMON)
    assert resumable_checkpoint(again) == str(last)
    assert _run_to_continue(again, ["train", "eval"]) == first
    with _tracked_run(again, ["train"]) as tracker:
        summary = train_denoiser(again, tracker, data_kind(again))
    assert tracker.run_id == first and client.get_run(first).info.status == "FINISHED"
    assert summary["steps"] == steps
    logged = [m.step for m in client.get_metric_history(first, "train_step_loss_diffuse")]
    assert logged == list(range(1, steps + 1))  # one point per step, across the requeue
    final, expected = (load_checkpoint(s["checkpoint"])["model"] for s in (summary, reference))
    for key, value in expected.items():
        assert torch.equal(final[key], value), key


def test_a_checkpoint_is_continued_only_by_the_configuration_that_wrote_it(smoke_data, tmp_path, caplog):
    cfg = smoke_config(smoke_data, tmp_path, [*COMMON, "task.train.max_steps=1", "tracking.enabled=false"])
    train_denoiser(cfg, _untracked_tracker(), data_kind(cfg))
    last = tmp_path / "checkpoints" / "last.pt"
    assert resumable_checkpoint(cfg) == str(last)
    # A key that decides the result differs: not continued, said once, naming the file.
    other_lr = smoke_config(smoke_data, tmp_path, [*COMMON, "task.train.max_steps=1", "task.train.lr=3e-4"])
    assert resumable_checkpoint(other_lr) is None
    assert f"{last}: not continued: written by another configuration" in caplog.text
    # Keys that change no result (where outputs go, tracking) still match.
    elsewhere = smoke_config(
        smoke_data, tmp_path, [*COMMON, "task.train.max_steps=1", "tracking.experiment=other", "stage=train"]
    )
    assert resumable_checkpoint(elsewhere) == str(last)
    # auto_resume=false: start over; an explicit resume is always continued, whoever wrote it.
    off = smoke_config(smoke_data, tmp_path, [*COMMON, "task.train.max_steps=1", "auto_resume=false"])
    assert resumable_checkpoint(off) is None
    explicit = smoke_config(
        smoke_data, tmp_path, [*COMMON, "task.train.lr=3e-4", f"task.train.resume={last}"]
    )
    assert resumable_checkpoint(explicit) == str(last)
    # A checkpoint from before checkpoints recorded their config's digest: not continued, and said so.
    state = load_checkpoint(last)
    del state["config_digest"]
    save_checkpoint(last, {k: v for k, v in state.items() if k != "format"})
    caplog.clear()
    assert resumable_checkpoint(cfg) is None
    assert "a version that recorded no configuration digest" in caplog.text


def test_the_first_checkpoint_is_written_before_the_first_step(smoke_data, tmp_path):
    """So that a job requeued during its first epoch continues its MLflow run instead of opening another."""
    cfg = smoke_config(smoke_data, tmp_path, COMMON)
    seen = []

    def on_step(step):
        if step == 1:
            seen.append(load_checkpoint(tmp_path / "checkpoints" / "last.pt"))
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt), _tracked_run(cfg, ["train"]) as tracker:
        train_denoiser(cfg, tracker, data_kind(cfg), on_step=on_step)
    assert seen[0]["step"] == 0 and seen[0]["mlflow_run_id"] == tracker.run_id


def test_an_exit_that_is_not_a_requeue_still_fails_the_run(smoke_data, tmp_path, fresh_flag):
    cfg = smoke_config(smoke_data, tmp_path, COMMON)

    def exits(step):
        if step == 2:
            sys.exit(3)

    with pytest.raises(SystemExit), _tracked_run(cfg, ["train"]) as tracker:
        train_denoiser(cfg, tracker, data_kind(cfg), on_step=exits)
    assert MlflowClient(cfg.tracking.uri).get_run(tracker.run_id).info.status == "FAILED"
    assert load_checkpoint(tmp_path / "checkpoints" / "last.pt")["step"] == 2  # saved on the way out


def _untracked_tracker():
    from src.tracking.tracker import Tracker

    return Tracker(None)
