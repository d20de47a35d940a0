"""The volumetric feature catalogue (`src.data.volume_features`) by value: the buffers and their channel
suffixes, the candidates in storage order, channel names and counts of a selection, the one-line errors,
a run's recorded features and the channel positions in prepared data. Fast, no data: the mutation group
`feature_selection` runs it (tests/test_volume_shards.py checks the same names against stored shards)."""

from __future__ import annotations

import pytest

from src.data.volume_features import (
    VOLUME_CANDIDATE_CHANNELS,
    VOLUME_CANDIDATE_FEATURES,
    VOLUME_FEATURE_BUFFERS,
    _suffixes,
    volume_channel_indices,
    volume_feature_channels,
    volume_feature_count,
)
from src.errors import ConfigError, DataError

RGB, XYZ, ONE = ("r", "g", "b"), ("x", "y", "z"), ("",)
#: Every feature buffer in storage order with its channel suffixes, written out.
BUFFERS = {
    "color": RGB,
    "surface": RGB,
    "volume": RGB,
    "volume_single": RGB,
    "volume_multi": RGB,
    "albedo": RGB,
    "normal": XYZ,
    "depth": ONE,
    "visibility": ONE,
    "transmittance": RGB,
    "optical_thickness": RGB,
    "scatter_depth": ONE,
    "scatter_media_distance": ONE,
    "sigma_t": RGB,
    "sigma_s": RGB,
    "scatter_albedo": RGB,
    "scattered": ONE,
    "volume_events": ONE,
    "motion": ("x", "y"),
}


def test_the_buffers_and_their_channel_suffixes():
    assert dict(VOLUME_FEATURE_BUFFERS) == BUFFERS
    assert list(VOLUME_FEATURE_BUFFERS) == list(BUFFERS)  # the storage order
    # the helper that builds them at import, called here so that its mutants can be seen
    got = {b: _suffixes(b, n) for b, n in [("color", 3), ("normal", 3), ("depth", 1), ("motion", 2)]}
    assert got == {"color": RGB, "normal": XYZ, "depth": ONE, "motion": ("x", "y")}


def test_the_candidates_are_each_buffer_then_its_variance_but_motion_has_none():
    expected = [f for b in BUFFERS if b != "motion" for f in (b, f"{b}.var")] + ["motion"]
    assert list(VOLUME_CANDIDATE_FEATURES) == expected and len(expected) == 37
    assert len(VOLUME_CANDIDATE_CHANNELS) == 62 == sum(len(s) + 1 for s in BUFFERS.values()) - 1
    assert VOLUME_CANDIDATE_CHANNELS[:8] == (
        "color_r", "color_g", "color_b", "color_var", "surface_r", "surface_g", "surface_b", "surface_var",
    )  # fmt: skip
    assert VOLUME_CANDIDATE_CHANNELS[-3:] == ("volume_events_var", "motion_x", "motion_y")


def test_a_selection_names_its_channels_in_the_order_written():
    features = ["normal", "motion", "depth.var", "color", "scattered", "sigma_t.var"]
    names = (
        "normal_x", "normal_y", "normal_z", "motion_x", "motion_y", "depth_var", "color_r", "color_g",
        "color_b", "scattered", "sigma_t_var",
    )  # fmt: skip
    assert volume_feature_channels(features) == names
    assert volume_feature_count(features) == 11
    assert volume_feature_count(["depth"]) == 1 and volume_feature_count(None) == 62
    assert volume_feature_channels(None) == VOLUME_CANDIDATE_CHANNELS
    assert volume_feature_channels(("color",)) == ("color_r", "color_g", "color_b")  # any sequence


EXAMPLE = "e.g. [color, color.var, albedo, normal, depth, transmittance, motion], or null for all"


@pytest.mark.parametrize(
    ("features", "shown"),
    [("color", "'color'"), ({"color"}, "{'color'}"), ({"color": 1}, "{'color': 1}"), ([], "[]")],
)
def test_a_selection_that_is_not_a_list_is_one_line_with_an_example(features, shown):
    with pytest.raises(ConfigError) as err:
        volume_feature_channels(features)
    assert (
        str(err.value) == f"dataset.volume_features={shown}: expected a non-empty list of features, {EXAMPLE}"
    )


def test_channel_positions_in_the_prepared_data_and_the_missing_one_named():
    stored = ["depth", "color_r", "color_g", "color_b", "motion_x"]
    assert volume_channel_indices(["color_b", "depth", "color_r"], stored, "shards/train") == [3, 0, 1]
    with pytest.raises(DataError) as err:
        volume_channel_indices(["depth", "motion_y", "normal_x"], stored, "shards/train")
    assert str(err.value) == (
        "shards/train: no channel 'motion_y' for dataset.volume_features (2 missing); run stage=preprocess "
        "dataset=volumetric again to store every candidate"
    )


@pytest.mark.parametrize(
    ("features", "index", "bad"),
    [
        (["color", "colour"], 1, "colour"),
        (["position"], 0, "position"),  # rendered, never an input
        (["depth", "motion.var"], 1, "motion.var"),
        (["color.grad"], 0, "color.grad"),
        (["depth.var.var"], 0, "depth.var.var"),
    ],
)
def test_an_unknown_feature_is_one_line_naming_its_index(features, index, bad):
    with pytest.raises(ConfigError) as err:
        volume_feature_channels(features)
    assert str(err.value) == (
        f"dataset.volume_features[{index}]={bad!r}: expected a buffer of {list(BUFFERS)}, optionally with "
        ".var (not motion)"
    )


def test_a_repeated_feature_is_one_line():
    with pytest.raises(ConfigError) as err:
        volume_feature_channels(["depth", "color", "depth", "motion", "color"])
    assert str(err.value) == "dataset.volume_features: ['color', 'depth'] listed more than once"
