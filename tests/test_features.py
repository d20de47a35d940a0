"""`task.features`: which channels a denoiser sees, their names and count, and the errors for bad lists."""

import pytest

from src.data.features import (
    CANDIDATE_CHANNELS,
    PAPER_CHANNELS,
    channel_indices,
    check_trained_features,
    feature_channels,
    feature_count,
)
from src.errors import ConfigError, DataError
from tests.conftest import compose_config, one_line_error

#: Bako et al. 2017 Sec. 4.1 / seed thesis Sec. 4.3, written out: what the paper profile must feed.
THESIS_28 = [
    *("color_r", "color_g", "color_b", "color_var"),
    *(f"color_d{a}_{c}" for a in "xy" for c in "rgb"),
    "normal_var",
    *(f"normal_d{a}_{c}" for a in "xy" for c in "xyz"),
    *("depth", "depth_var", "depth_dx_z", "depth_dy_z"),
    "albedo_var",
    *(f"albedo_d{a}_{c}" for a in "xy" for c in "rgb"),
]


def test_the_paper_set_is_the_thesis_28_channels_in_order():
    assert list(PAPER_CHANNELS) == THESIS_28
    assert set(PAPER_CHANNELS) < set(CANDIDATE_CHANNELS) and len(CANDIDATE_CHANNELS) == 38


def test_channels_follow_the_order_written_and_are_counted():
    features = ["visibility.grad", "visibility", "albedo", "normal.var"]
    assert feature_channels(features) == (
        "visibility_dx_v",
        "visibility_dy_v",
        "visibility",
        "albedo_r",
        "albedo_g",
        "albedo_b",
        "normal_var",
    )
    assert feature_count(features) == 7
    assert (
        feature_count([f"{b}{c}" for b in ("color", "normal", "albedo") for c in ("", ".var", ".grad")]) == 30
    )


@pytest.mark.parametrize(
    ("features", "needles"),
    [
        (["color", "colour"], ["task.features[1]='colour'", "'color'", ".var or .grad"]),
        (["color.mean"], ["task.features[0]='color.mean'", ".var or .grad"]),
        (["color", "albedo", "color"], ["task.features", "['color'] listed more than once"]),
        ([], ["task.features", "non-empty list"]),
        ("color", ["task.features='color'", "list"]),
        ({"color": ["var"]}, ["task.features", "list"]),
    ],
)
def test_a_bad_feature_list_is_one_line_naming_the_key(features, needles):
    with pytest.raises(ConfigError) as excinfo:
        feature_channels(features)
    one_line_error(excinfo, *needles)


def test_channels_are_found_by_name_or_the_data_are_named_stale():
    assert channel_indices(["b", "a"], ["a", "b", "c"], "x") == [1, 0]
    with pytest.raises(DataError) as excinfo:
        channel_indices(["visibility", "a"], ["a"], "prepared/index.json")
    one_line_error(excinfo, "prepared/index.json", "'visibility'", "stage=preprocess")


def test_a_checkpoint_evaluates_only_with_the_features_it_was_trained_on():
    paper = ["color", "color.var", "color.grad", "normal.var", "normal.grad"]
    paper += ["depth", "depth.var", "depth.grad", "albedo.var", "albedo.grad"]
    check_trained_features(None, paper, "old.pt")  # checkpoints before task.features: the paper set
    check_trained_features(["albedo"], ["albedo"], "a.pt")
    with pytest.raises(DataError) as excinfo:
        check_trained_features(["albedo"], ["normal"], "runs/final.pt")
    one_line_error(excinfo, "runs/final.pt", "task.features=[albedo]", "configured [normal]")


def test_model_in_channels_are_derived_from_the_feature_list():
    assert compose_config(["model=kpcn"]).model.in_channels == 28
    cfg = compose_config(["model=resnet", "task.features=[color,visibility,visibility.grad]"])
    assert cfg.model.in_channels == 6
    cfg = compose_config(["model=dpcn", "task.features=[albedo,normal]"])
    assert cfg.model.in_channels == 6
