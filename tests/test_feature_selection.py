"""Feature-selection building blocks (src.train.feature_selection): feature dropout, neutral values, greedy
forward selection on a synthetic problem with a trained probe, and the selected / random arms."""

from __future__ import annotations

import pytest
import torch

from src.errors import ConfigError
from src.train.feature_selection import (
    drop_features,
    feature_slices,
    greedy_forward_selection,
    keep_only,
    neutral_values,
    random_features,
    random_keep_mask,
    selected_features,
    spread_indices,
)

FEATURES = ["color", "albedo", "albedo.var", "transmittance", "depth", "motion"]  # 3+3+1+3+1+2 = 13


def test_feature_slices_follow_channel_counts():
    slices = feature_slices(FEATURES)
    assert [name for name, _ in slices] == FEATURES
    assert [(s.start, s.stop) for _, s in slices] == [(0, 3), (3, 6), (6, 7), (7, 10), (10, 11), (11, 13)]


def test_neutral_values_default_zero_and_overrides():
    assert torch.equal(neutral_values(FEATURES, {}), torch.zeros(13))
    v = neutral_values(FEATURES, {"transmittance": 1.0, "albedo.var": -2.0, "visibility": 1.0})
    expected = torch.zeros(13)
    expected[7:10] = 1.0  # by buffer name: the value channels only
    expected[6] = -2.0  # by full feature name
    assert torch.equal(v, expected)
    # transmittance.var stays 0 while transmittance is 1
    assert torch.equal(neutral_values(["transmittance", "transmittance.var"], {"transmittance": 1.0}),
                       torch.tensor([1.0, 1.0, 1.0, 0.0]))  # fmt: skip


def test_neutral_values_unknown_key_is_one_line_config_error():
    with pytest.raises(ConfigError, match=r"task\.feature_selection\.neutral") as err:
        neutral_values(FEATURES, {"transmitance": 1.0})
    assert "\n" not in str(err.value)
    with pytest.raises(ConfigError, match=r"task\.feature_selection\.neutral"):
        neutral_values(FEATURES, {"motion.var": 0.0})


@pytest.mark.parametrize("layout", ["frame", "sequence"])
def test_drop_features_sets_exact_neutral_and_keeps_the_rest(layout):
    g = torch.Generator().manual_seed(0)
    n = 5
    shape = (n, 13, 4, 6) if layout == "frame" else (n, 3, 13, 4, 6)
    axis = 1 if layout == "frame" else 2
    inputs = torch.randn(shape, generator=g)
    original = inputs.clone()
    slices = feature_slices(FEATURES)
    neutral = neutral_values(FEATURES, {"transmittance": 1.0, "depth": 0.37})
    keep = random_keep_mask(n, len(FEATURES), 0.5, g, always_keep=[0])
    keep[0, 1:] = False  # one sample with everything but colour dropped
    keep[1] = True  # one with everything kept
    out = drop_features(inputs, keep, slices, neutral, channel_axis=axis)
    assert torch.equal(inputs, original)  # not modified in place
    assert out.shape == inputs.shape
    for i in range(n):
        for f, (_, s) in enumerate(slices):
            got = out[i, :, s] if layout == "sequence" else out[i, s]
            was = inputs[i, :, s] if layout == "sequence" else inputs[i, s]
            if keep[i, f]:
                assert torch.equal(got, was)
            else:
                shape_c = (1, -1, 1, 1) if layout == "sequence" else (-1, 1, 1)
                assert torch.equal(got, neutral[s].reshape(shape_c).expand_as(got))
    assert not torch.equal(out, inputs)  # something was dropped


def test_drop_features_checks_shapes():
    slices = feature_slices(FEATURES)
    with pytest.raises(ValueError, match="neutral"):
        drop_features(torch.zeros(2, 13, 1, 1), torch.ones(2, 6, dtype=torch.bool), slices, torch.zeros(12))
    with pytest.raises(ValueError, match="keep"):
        drop_features(torch.zeros(2, 13, 1, 1), torch.ones(3, 6, dtype=torch.bool), slices, torch.zeros(13))


def test_random_keep_mask_rate_and_always_keep():
    g = torch.Generator().manual_seed(1)
    keep = random_keep_mask(20000, 6, 0.3, g, always_keep=[0, 4])
    assert keep.shape == (20000, 6) and keep.dtype == torch.bool
    assert keep[:, [0, 4]].all()
    drop_rate = 1 - keep[:, [1, 2, 3, 5]].float().mean(dim=0)
    assert torch.allclose(drop_rate, torch.full((4,), 0.3), atol=0.015)
    assert keep[:, 1:4].any(dim=1).float().mean() < 1  # independent: some rows drop all of them
    assert random_keep_mask(10, 3, 0.0).all() and not random_keep_mask(10, 3, 1.0).any()
    with pytest.raises(ConfigError, match=r"task\.feature_selection\.dropout"):
        random_keep_mask(10, 3, 1.5)


def test_keep_only():
    assert keep_only(["color", "depth"], FEATURES).tolist() == [True, False, False, False, True, False]
    assert keep_only([], FEATURES).tolist() == [False] * 6
    with pytest.raises(ConfigError, match="normal"):
        keep_only(["normal"], FEATURES)


def test_greedy_rows_ties_and_max_size():
    cost = {"a": 3.0, "b": 1.0, "c": 1.0, "d": 2.0}  # b and c tie: b (earlier) first

    def loss_of(selected):
        return 10.0 - sum(cost.get(f, 0.0) for f in selected)

    rows = greedy_forward_selection(loss_of, ["color", "d", "c", "b", "a"], ["color"], progress=False)
    assert [r["round"] for r in rows] == [0, 1, 2, 3, 4]
    assert rows[0] == {"round": 0, "added": None, "features": ["color"], "loss": 10.0}
    assert [r["added"] for r in rows[1:]] == ["a", "d", "c", "b"]  # c before b: candidate order
    assert rows[-1]["features"] == ["color", "a", "d", "c", "b"]
    assert [r["loss"] for r in rows] == [10.0, 7.0, 5.0, 4.0, 3.0]
    short = greedy_forward_selection(loss_of, ["a", "b", "c", "d"], ["color"], max_size=2, progress=False)
    assert [r["added"] for r in short] == [None, "a", "d"]
    assert len(greedy_forward_selection(loss_of, ["a"], ["color"], max_size=0, progress=False)) == 1


def test_greedy_nan_loss_never_wins():
    rows = greedy_forward_selection(
        lambda s: float("nan") if "x" in s else float(len(s)), ["x", "y"], [], max_size=1, progress=False
    )
    assert rows[1]["added"] == "y"


# Synthetic problem: the target is the colour plus visibility and sigma_t; four distractors come first.
SYN_FEATURES = ["color", "normal", "depth", "albedo", "transmittance", "visibility", "sigma_t"]
SIGNAL = {"visibility", "sigma_t"}


def _synthetic(n, g):
    slices = feature_slices(SYN_FEATURES)
    c = slices[-1][1].stop
    x = torch.randn(n, c, 4, 4, generator=g)
    by = {name: x[:, s] for name, s in slices}
    target = by["color"] + 1.5 * by["visibility"] - 1.0 * by["sigma_t"]
    target = target + 0.05 * torch.randn(target.shape, generator=g)
    return x, target


def test_greedy_with_probe_picks_the_signal_features_first():
    torch.manual_seed(0)
    g = torch.Generator().manual_seed(0)
    slices = feature_slices(SYN_FEATURES)
    neutral = neutral_values(SYN_FEATURES, {"transmittance": 1.0})
    x_train, y_train = _synthetic(32, g)
    x_val, y_val = _synthetic(32, g)
    probe = torch.nn.Conv2d(x_train.shape[1], 3, kernel_size=1)
    opt = torch.optim.Adam(probe.parameters(), lr=0.1)
    for _ in range(150):
        keep = random_keep_mask(len(x_train), len(SYN_FEATURES), 0.5, g, always_keep=[0])
        loss = torch.nn.functional.mse_loss(probe(drop_features(x_train, keep, slices, neutral)), y_train)
        opt.zero_grad()
        loss.backward()
        opt.step()

    @torch.no_grad()
    def val_loss(selected):
        keep = keep_only(selected, SYN_FEATURES).expand(len(x_val), -1)
        return torch.nn.functional.mse_loss(probe(drop_features(x_val, keep, slices, neutral)), y_val).item()

    rows = greedy_forward_selection(val_loss, SYN_FEATURES[1:], ["color"], progress=False)
    assert {rows[1]["added"], rows[2]["added"]} == SIGNAL
    losses = [r["loss"] for r in rows]
    assert losses[0] > losses[1] > losses[2]  # falls ...
    gain = losses[0] - losses[2]
    assert all(abs(loss - losses[2]) < 0.05 * gain for loss in losses[3:])  # ... then flattens
    assert selected_features(rows, 2)[0] == "color" and set(selected_features(rows, 2)[1:]) == SIGNAL


def test_selected_features_sizes_and_errors():
    rows = greedy_forward_selection(lambda s: -len(s), ["a", "b", "c"], ["color"], progress=False)
    assert selected_features(rows, 0) == ["color"]
    assert selected_features(rows, 2) == ["color", "a", "b"]
    assert selected_features(rows, 3) == ["color", "a", "b", "c"]
    for bad in (4, -1):
        with pytest.raises(ConfigError, match=r"task\.feature_selection\.size") as err:
            selected_features(rows, bad)
        assert "\n" not in str(err.value)


def test_random_features_sizes_seed_and_errors():
    candidates = ["color", "a", "b", "c", "d", "e"]
    picked = random_features(candidates, ["color"], 3, seed=7)
    assert len(picked) == 4 and picked[0] == "color" and len(set(picked)) == 4
    assert set(picked[1:]) <= {"a", "b", "c", "d", "e"}
    assert random_features(candidates, ["color"], 3, seed=7) == picked  # deterministic
    assert random_features(candidates, ["color"], 4, seed=7)[:4] == picked  # nested over size
    draws = {tuple(random_features(candidates, ["color"], 2, seed=s)) for s in range(20)}
    assert len(draws) > 3  # actually random over seeds
    assert random_features(candidates, ["color"], 0, seed=0) == ["color"]
    for bad in (6, -1):
        with pytest.raises(ConfigError, match=r"task\.feature_selection\.size"):
            random_features(candidates, ["color"], bad, seed=0)


def test_spread_indices_cover_the_whole_validation_set():
    assert spread_indices(12, 4) == [0, 3, 6, 9]
    assert spread_indices(12, None) == list(range(12))
    assert spread_indices(3, 5) == [0, 1, 2]
    assert spread_indices(10, 3) == [0, 3, 6]
