"""KPCN buffer convention: exact round trip, one-line errors for each bad input, counted repairs."""

import logging

import numpy as np
import pytest

from src.data.exr_buffers import BufferLayout, RepairPolicy, buffers_to_channels, load_buffers, write_buffers
from src.data.kpcn_buffers import (
    KPCN_BUFFERS,
    KPCN_LAYOUT,
    OPTIONAL_BUFFERS,
    load_kpcn_exr,
    write_kpcn_exr,
)
from src.errors import ConfigError, DataError
from src.io.exr import read_exr, write_exr
from tests.conftest import one_line_error

H, W = 7, 5  # non-square on purpose


def make_buffers(seed=0, h=H, w=W):
    rng = np.random.default_rng(seed)
    out = {name: rng.random((h, w, len(chans)), dtype=np.float32) for name, chans in KPCN_BUFFERS.items()}
    out["normal"] = out["normal"] * 2 - 1  # normals may legitimately be negative
    return out


def write_channels(path, **overrides):
    """Write a valid KPCN file with some channels replaced (value) or dropped (None)."""
    channels = buffers_to_channels(KPCN_LAYOUT, make_buffers())
    for name, value in overrides.items():
        name = name.replace("__", ".")
        if value is None:
            del channels[name]
        else:
            channels[name] = value
    write_exr(path, channels)
    return path


def test_spec_names_exactly_the_tungsten_convention():
    assert KPCN_BUFFERS["color"] == ("R", "G", "B")
    for b in ("diffuse", "specular", "albedo", "normal"):
        assert KPCN_BUFFERS[b] == (f"{b}.R", f"{b}.G", f"{b}.B")
    assert KPCN_BUFFERS["depth"] == ("depth.Z",) and KPCN_BUFFERS["visibility"] == ("visibility.Z",)
    for b in ("color", "diffuse", "specular", "albedo", "normal", "depth", "visibility"):
        assert KPCN_BUFFERS[f"{b}Variance"] == (f"{b}Variance.Z",)
    # The GP filters' features (Davletaliyev 2016), optional: older files lack them.
    assert KPCN_BUFFERS["position"] == ("position.R", "position.G", "position.B")
    assert KPCN_BUFFERS["secondary_albedo"] == tuple(f"secondary_albedo.{c}" for c in "RGB")
    assert KPCN_BUFFERS["positionVariance"] == ("positionVariance.Z",)
    assert KPCN_BUFFERS["secondary_albedoVariance"] == ("secondary_albedoVariance.Z",)
    assert len(KPCN_BUFFERS) == 18 and sum(map(len, KPCN_BUFFERS.values())) == 32
    assert set(OPTIONAL_BUFFERS) == {
        "position",
        "secondary_albedo",
        "positionVariance",
        "secondary_albedoVariance",
    }


def test_files_without_the_optional_buffers_still_load(tmp_path):
    """Real KPCN data and older renders have no position / secondary albedo: they load without those keys;
    asking for one by name, or a file with only part of one, is the missing-channel error."""
    old = {k: v for k, v in make_buffers().items() if k not in OPTIONAL_BUFFERS}
    path = write_kpcn_exr(tmp_path / "old-00004spp.exr", old)
    loaded, _ = load_kpcn_exr(path, expected_size=(H, W))
    assert list(loaded) == [b for b in KPCN_BUFFERS if b not in OPTIONAL_BUFFERS]
    for name, arr in old.items():
        np.testing.assert_array_equal(loaded[name], arr)
    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(path, buffers=["color", "position"])
    one_line_error(excinfo, "missing EXR channels", "position.R")
    partial = write_channels(tmp_path / "partial.exr", position__G=None)
    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(partial)
    one_line_error(excinfo, "missing EXR channel", "position.G")


def test_round_trip(tmp_path):
    buffers = make_buffers()
    path = write_kpcn_exr(tmp_path / "scene-00004spp.exr", buffers)
    assert sorted(read_exr(path)) == sorted(ch for chans in KPCN_BUFFERS.values() for ch in chans)
    loaded, report = load_kpcn_exr(path, expected_size=(H, W))
    assert list(loaded) == list(KPCN_BUFFERS)
    for name, arr in buffers.items():
        assert loaded[name].dtype == np.float32
        assert loaded[name].shape == (H, W, len(KPCN_BUFFERS[name]))
        np.testing.assert_array_equal(loaded[name], arr)
    assert report.total == 0 and report.summary() == "no repairs"


def test_single_channel_buffers_accept_2d_and_subset_load(tmp_path):
    buffers = {"color": make_buffers()["color"], "depth": np.full((H, W), 2.5, np.float64)}
    path = write_kpcn_exr(tmp_path / "ref.exr", buffers)
    loaded, _ = load_kpcn_exr(path, buffers=["depth", "color"])
    assert list(loaded) == ["depth", "color"]
    assert loaded["depth"].shape == (H, W, 1) and loaded["depth"].dtype == np.float32
    np.testing.assert_array_equal(loaded["depth"], 2.5)


def test_buffers_to_channels_rejects_bad_input():
    with pytest.raises(DataError) as excinfo:
        buffers_to_channels(KPCN_LAYOUT, {"colour": np.zeros((H, W, 3))})
    one_line_error(excinfo, "'colour'")
    with pytest.raises(DataError) as excinfo:
        buffers_to_channels(KPCN_LAYOUT, {"normal": np.zeros((H, W, 1))})
    one_line_error(excinfo, "'normal'", "(H, W, 3)")


def test_missing_channel(tmp_path):
    path = write_channels(tmp_path / "nodiffG.exr", diffuse__G=None)
    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(path)
    one_line_error(
        excinfo, "nodiffG.exr", "missing EXR channel 'diffuse.G' (buffer 'diffuse'); found: B, G, R,"
    )


def test_many_missing_channels_stay_one_line(tmp_path):
    path = write_exr(tmp_path / "rgb_only.exr", {c: np.ones((H, W), np.float32) for c in "RGB"})
    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(path)
    one_line_error(excinfo, "rgb_only.exr", "'diffuse.R' (buffer 'diffuse')", "more", "found: B, G, R")


def test_wrong_expected_size(tmp_path):
    path = write_kpcn_exr(tmp_path / "small.exr", make_buffers())
    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(path, expected_size=(W, H))
    one_line_error(excinfo, "small.exr", "7x5", "expected 5x7")


def test_non_float_channel_rejected(tmp_path):
    path = write_channels(tmp_path / "uint.exr", depth__Z=np.ones((H, W), np.uint32))
    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(path)
    one_line_error(excinfo, "uint.exr", "'depth.Z'", "uint32")


def _with(channel, index, value, dtype=np.float32):
    arr = np.asarray(buffers_to_channels(KPCN_LAYOUT, make_buffers())[channel], dtype=dtype).copy()
    for i in np.atleast_1d(index):
        arr.flat[i] = value
    return arr


@pytest.mark.parametrize(
    ("channel", "value", "needles"),
    [
        ("R", np.nan, ["'R' (buffer 'color')", "2 non-finite", "2 NaN"]),
        ("depth.Z", np.inf, ["'depth.Z' (buffer 'depth')", "2 non-finite", "2 Inf"]),
        ("albedoVariance.Z", -np.inf, ["'albedoVariance.Z'", "2 non-finite"]),
        ("diffuse.B", -0.5, ["'diffuse.B' (buffer 'diffuse')", "2 negative radiance"]),
        ("specular.R", -1e-3, ["'specular.R'", "2 negative radiance"]),
        ("specularVariance.Z", -2.0, ["'specularVariance.Z'", "2 negative variance"]),
    ],
)
def test_bad_values_error_then_repair(tmp_path, caplog, channel, value, needles):
    path = write_channels(
        tmp_path / "bad.exr", **{channel.replace(".", "__"): _with(channel, [3, 11], value)}
    )
    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(path)
    kind = "negative" if np.isfinite(value) else "nonfinite"
    fix = "negative=clamp" if kind == "negative" else "nonfinite=zero"
    one_line_error(excinfo, "bad.exr", *needles, f"repair with task.preprocess.repair.{fix}")

    policy = RepairPolicy(negative="clamp") if kind == "negative" else RepairPolicy(nonfinite="zero")
    with caplog.at_level(logging.WARNING, logger="src.data.kpcn_buffers"):
        loaded, report = load_kpcn_exr(path, repair=policy)
    assert report.counts == {kind: {channel: 2}} and report.total == 2
    assert report.summary() == f"{kind}: {channel}=2"
    buf = next(b for b, chans in KPCN_BUFFERS.items() if channel in chans)
    flat = loaded[buf][..., KPCN_BUFFERS[buf].index(channel)].ravel()
    assert flat[3] == 0 and flat[11] == 0
    records = [r for r in caplog.records if "bad.exr" in r.getMessage()]
    assert len(records) == 1 and "\n" not in records[0].getMessage() and channel in records[0].getMessage()


def test_negative_normals_are_not_errors(tmp_path):
    path = write_channels(tmp_path / "n.exr", normal__R=np.full((H, W), -1.0, np.float32))
    loaded, report = load_kpcn_exr(path)
    assert loaded["normal"].min() == -1.0 and report.total == 0


def test_firefly_clamp_only_touches_radiance_and_counts(tmp_path):
    buffers = make_buffers()
    buffers["color"][0, 0] = [50.0, 0.5, 80.0]
    buffers["diffuse"][1, 1, 0] = 30.0
    buffers["albedo"][2, 2, 0] = 40.0  # not radiance: untouched
    buffers["colorVariance"][0, 0, 0] = 1e4  # variances are never clamped
    path = write_kpcn_exr(tmp_path / "fire.exr", buffers)
    loaded, report = load_kpcn_exr(path, repair=RepairPolicy(firefly_clamp=10.0))
    assert report.counts == {"firefly": {"R": 1, "B": 1, "diffuse.R": 1}}
    np.testing.assert_array_equal(loaded["color"][0, 0], [10.0, 0.5, 10.0])
    assert loaded["diffuse"][1, 1, 0] == 10.0
    assert loaded["albedo"][2, 2, 0] == 40.0 and loaded["colorVariance"][0, 0, 0] == 1e4
    assert loaded["specular"].max() <= 10.0


def test_combined_repairs_counted_per_channel(tmp_path):
    path = write_channels(
        tmp_path / "combo.exr",
        R=_with("R", [0, 1, 2], np.nan),
        diffuse__G=_with("diffuse.G", [4], -1.0),
        specular__B=_with("specular.B", [5, 6], 1e6),
    )
    policy = RepairPolicy(nonfinite="zero", negative="clamp", firefly_clamp=100.0)
    _, report = load_kpcn_exr(path, repair=policy)
    assert report.counts == {
        "nonfinite": {"R": 3},
        "negative": {"diffuse.G": 1},
        "firefly": {"specular.B": 2},
    }
    assert report.total == 6
    assert report.summary() == "nonfinite: R=3; negative: diffuse.G=1; firefly: specular.B=2"


def test_aliases_map_differently_named_files(tmp_path):
    channels = buffers_to_channels(KPCN_LAYOUT, make_buffers())
    for c, alias in zip("RGB", "XYZ", strict=True):
        channels[f"normal.{alias}"] = channels.pop(f"normal.{c}")
    path = write_exr(tmp_path / "xyz.exr", channels)
    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(path)
    one_line_error(excinfo, "xyz.exr", "'normal.R' (buffer 'normal')", "normal.X")
    aliases = {"normal.R": "normal.X", "normal.G": "normal.Y", "normal.B": "normal.Z"}
    loaded, _ = load_kpcn_exr(path, aliases=aliases)
    np.testing.assert_array_equal(loaded["normal"], make_buffers()["normal"])

    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(path, aliases={"normal.R": "N.x"})
    one_line_error(excinfo, "xyz.exr", "'N.x' (alias of 'normal.R', buffer 'normal')")
    with pytest.raises(ConfigError) as excinfo:
        load_kpcn_exr(path, aliases={"normal.W": "normal.X"})
    one_line_error(excinfo, "aliases", "'normal.W'")


def test_repair_policy_validates_and_is_frozen():
    assert RepairPolicy() == RepairPolicy(nonfinite="error", negative="error", firefly_clamp=None)
    for (key, value), expected in (
        (("nonfinite", "zeros"), "expected 'error' or 'zero'"),
        (("negative", "abs"), "expected 'error' or 'clamp'"),
        (("firefly_clamp", 0.0), "expected null or a positive number"),
        (("firefly_clamp", np.inf), "expected null or a positive number"),
    ):
        with pytest.raises(ConfigError) as excinfo:
            RepairPolicy(**{key: value})
        one_line_error(excinfo, f"task.preprocess.repair.{key}={value!r}", expected)
    with pytest.raises(AttributeError):
        RepairPolicy().negative = "clamp"


def test_unreadable_file_is_data_error(tmp_path):
    path = tmp_path / "junk.exr"
    path.write_bytes(b"\x76\x2f\x31\x01" + b"\x00" * 64)  # EXR magic, then nonsense
    with pytest.raises(DataError) as excinfo:
        load_kpcn_exr(path)
    one_line_error(excinfo, "junk.exr")


def test_another_kind_of_data_gets_every_check_by_declaring_its_layout(tmp_path):
    """A layout other than KPCN's (e.g. volumetric frames) is validated by the same loader."""
    channels = {"scatter": ("scatter.R", "scatter.G", "scatter.B"), "densityVariance": ("densityVariance.Z",)}
    layout = BufferLayout("volume", channels, radiance=("scatter",), variance=("densityVariance",))
    good = {"scatter": np.ones((H, W, 3)), "densityVariance": np.zeros((H, W, 1))}
    write_buffers(tmp_path / "ok.exr", layout, good)
    loaded, _ = load_buffers(tmp_path / "ok.exr", layout)
    np.testing.assert_array_equal(loaded["scatter"], good["scatter"])
    bad = {**good, "densityVariance": -np.ones((H, W, 1))}
    write_buffers(tmp_path / "neg.exr", layout, bad)
    with pytest.raises(DataError) as excinfo:
        load_buffers(tmp_path / "neg.exr", layout)
    one_line_error(excinfo, "neg.exr", "densityVariance.Z", "negative variance")
    write_buffers(tmp_path / "part.exr", layout, {"scatter": good["scatter"]})
    with pytest.raises(DataError) as excinfo:
        load_buffers(tmp_path / "part.exr", layout)
    one_line_error(excinfo, "part.exr", "missing EXR channel", "densityVariance.Z")
    with pytest.raises(ConfigError) as excinfo:
        load_buffers(tmp_path / "ok.exr", layout, buffers=["color"])
    one_line_error(excinfo, "unknown volume buffers", "'color'")
