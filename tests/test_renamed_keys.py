"""Keys that moved (src/report/renamed_keys.py): runs logged before the sequences' options moved from
`task:` to `dataset:` are read, by the reports and the ledger, under today's names, through a real MLflow
store; their command-line overrides too."""

from __future__ import annotations

import math

import mlflow
import pandas as pd
import pytest
from mlflow.entities import Param
from mlflow.tracking import MlflowClient

from src.report.collect import find_runs
from src.report.matched_arms import off_profile_key
from src.report.renamed_keys import RENAMED, renamed_key, renamed_params


@pytest.mark.parametrize(
    "old,new",
    [
        ("task.volume_features", "dataset.volume_features"),
        ("task.feature_selection.size", "dataset.feature_selection.size"),
        ("task.feature_selection.neutral.transmittance", "dataset.feature_selection.neutral.transmittance"),
        ("task.preprocess.volume_transform", "dataset.preprocess.volume_transform"),
        ("task.preprocess.sequence_frames", "dataset.preprocess.sequence_frames"),
        ("task.preprocess.patches_per_sequence", "dataset.preprocess.patches_per_sequence"),
        ("task.train.volumetric.temporal_weight", "dataset.train.temporal_weight"),
        ("task.train.volumetric.schedule._target_", "dataset.train.schedule._target_"),
        ("+task.feature_selection.order", "+dataset.feature_selection.order"),
        ("++task.volume_features", "++dataset.volume_features"),
        ("~task.train.volumetric", "~dataset.train"),
    ],
)
def test_a_moved_key_is_read_under_its_new_name_with_its_override_sign(old, new):
    assert renamed_key(old) == new


@pytest.mark.parametrize(
    "key",
    [
        "task.features",  # the still images' features stay the task's
        "task.preprocess.patch_size",  # shared by every denoising kind
        "task.preprocess.split",
        "task.train.lr",
        "task.train.volumetric_extra",  # shares the text, not the dotted prefix
        "task.volume_features_old",
        "dataset.train.loss",  # already today's
        "model.name",
    ],
)
def test_a_key_that_did_not_move_is_left_alone(key):
    assert renamed_key(key) == key


def test_every_rename_maps_a_task_key_to_a_dataset_key():
    assert all(old.startswith("task.") and new.startswith("dataset.") for old, new in RENAMED.items())


def test_old_and_new_columns_become_one_each_run_keeping_what_it_logged():
    runs = pd.DataFrame(
        {
            "run_id": ["old", "new", "both"],
            "params.task.train.volumetric.temporal_weight": ["0.0", None, "9"],
            "params.dataset.train.temporal_weight": [None, "0.5", "0.25"],
            "params.task.volume_features": ["['color']", None, None],
            "params.model.name": ["unet_kpcn"] * 3,
            "metrics.eval_psnr": [30.0, 31.0, 32.0],
        }
    )
    out = renamed_params(runs)
    assert (
        "params.task.train.volumetric.temporal_weight" not in out and "params.task.volume_features" not in out
    )
    assert list(out["params.dataset.train.temporal_weight"]) == ["0.0", "0.5", "0.25"]  # today's value wins
    assert out["params.dataset.volume_features"].iloc[0] == "['color']"
    assert math.isnan(out["params.dataset.volume_features"].iloc[1])
    assert list(out["params.model.name"]) == ["unet_kpcn"] * 3 and list(out["metrics.eval_psnr"]) == [
        30,
        31,
        32,
    ]
    unmoved = runs[["run_id", "params.model.name"]]
    assert renamed_params(unmoved) is unmoved


def test_the_reports_find_runs_logged_under_either_name_in_a_real_store(tmp_path):
    """One run logged before the move (`task.train.volumetric.temporal_weight`) and one after
    (`dataset.train.temporal_weight`), in a SQLite MLflow store: `find_runs` gives both under today's key."""
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path}/m.db")
    client = MlflowClient()
    experiment = client.create_experiment("renamed", artifact_location=str(tmp_path / "art"))
    for name, params in (
        ("before", {"task.train.volumetric.temporal_weight": "0.0", "task.feature_selection.size": "4"}),
        ("after", {"dataset.train.temporal_weight": "0.5", "dataset.feature_selection.size": "4"}),
    ):
        run = client.create_run(experiment, run_name=name).info.run_id
        client.log_batch(run, params=[Param(k, v) for k, v in {**params, "model.name": "unet_kpcn"}.items()])
        client.set_terminated(run)
    runs = find_runs({"experiment": "renamed"}).set_index("tags.mlflow.runName")
    assert runs.loc["before", "params.dataset.train.temporal_weight"] == "0.0"
    assert runs.loc["after", "params.dataset.train.temporal_weight"] == "0.5"
    assert set(runs["params.dataset.feature_selection.size"]) == {"4"}
    assert not [c for c in runs.columns if c.startswith("params.task.")]


def test_an_old_runs_overrides_are_judged_under_todays_names():
    """A run's `nrbench.hydra_job` tag holds the overrides as typed then: the study's arm (allowed) and a
    profile's budget key are recognised under their old names too."""
    allowed = ["dataset.train.temporal_weight"]
    budget = frozenset({"dataset.preprocess.sequence_frames", "task.train.epochs"})
    assert off_profile_key("task.train.volumetric.temporal_weight=0.0 seed=3", budget, allowed) == ""
    assert off_profile_key("dataset.train.temporal_weight=0.0 seed=3", budget, allowed) == ""
    moved = "task.train.volumetric.temporal_weight=0.0 task.preprocess.sequence_frames=5"
    assert off_profile_key(moved, budget, allowed) == "dataset.preprocess.sequence_frames"
    assert off_profile_key("task.train.epochs=2", budget, allowed) == "task.train.epochs"
