"""EXR IO: exact round trips with flat channel names, atomic writes, one-line errors naming the file."""

import numpy as np
import OpenEXR
import pytest

from src.data.kpcn_buffers import KPCN_BUFFERS
from src.errors import DataError
from src.io import exr
from src.io.atomic import atomic_path, atomic_write_bytes, atomic_write_text
from src.io.exr import exr_channel_names, exr_size, read_exr, write_exr
from tests.conftest import one_line_error

H, W = 7, 5  # non-square on purpose
SPEC_CHANNELS = [ch for chans in KPCN_BUFFERS.values() for ch in chans]


def _values(rng, dtype, shape=(H, W)):
    if dtype == np.uint32:
        return rng.integers(0, 2**32, size=shape, dtype=np.uint32)
    arr = (rng.standard_normal(shape) * 100).astype(dtype)
    arr.flat[:4] = [0.0, -0.0, np.finfo(dtype).max, np.finfo(dtype).tiny]
    return arr


def _tmp_leftovers(directory):
    return [p.name for p in directory.iterdir() if ".tmp-" in p.name]


@pytest.mark.parametrize("dtype", [np.float32, np.float16, np.uint32])
def test_round_trip_every_spec_channel_exact(tmp_path, dtype):
    rng = np.random.default_rng(0)
    channels = {name: _values(rng, dtype) for name in SPEC_CHANNELS}
    path = tmp_path / "all.exr"
    write_exr(path, channels)
    back = read_exr(path)
    assert sorted(back) == sorted(SPEC_CHANNELS)  # flat names: no "RGB" or "diffuse" grouping
    assert sorted(exr_channel_names(path)) == sorted(SPEC_CHANNELS)
    assert exr_size(path) == (H, W)
    for name, arr in channels.items():
        assert back[name].shape == (H, W)
        assert back[name].dtype == dtype
        np.testing.assert_array_equal(back[name], arr)


def test_mixed_dtypes_subset_and_nonfinite_values(tmp_path):
    rng = np.random.default_rng(1)
    f32 = _values(rng, np.float32)
    f32[1, 2], f32[3, 4], f32[6, 0] = np.nan, np.inf, -np.inf
    channels = {"R": f32, "depth.Z": _values(rng, np.float16), "id": _values(rng, np.uint32)}
    path = tmp_path / "mixed.exr"
    write_exr(path, channels)
    back = read_exr(path, ["id", "R"])
    assert list(back) == ["id", "R"]
    assert back["R"].dtype == np.float32 and back["id"].dtype == np.uint32
    np.testing.assert_array_equal(back["R"], f32)
    np.testing.assert_array_equal(back["id"], channels["id"])


def test_non_contiguous_input_and_caller_dict_untouched(tmp_path):
    """OpenEXR 3.5 scrambles non-contiguous arrays and replaces the dict's values: we must not."""
    view = np.arange(H * W, dtype=np.float32).reshape(W, H).T
    channels = {"R": view}
    write_exr(tmp_path / "view.exr", channels)
    assert channels["R"] is view
    np.testing.assert_array_equal(read_exr(tmp_path / "view.exr")["R"], view)


@pytest.mark.parametrize("compression", sorted(exr.COMPRESSIONS))
def test_every_offered_compression_is_lossless(tmp_path, compression):
    arr = _values(np.random.default_rng(2), np.float32)
    write_exr(tmp_path / "c.exr", {"diffuse.R": arr}, compression=compression)
    np.testing.assert_array_equal(read_exr(tmp_path / "c.exr")["diffuse.R"], arr)


@pytest.mark.parametrize(
    ("channels", "needle"),
    [
        ({"R": np.zeros((H, W), np.float64)}, "'R'"),
        ({"R": np.zeros((H, W), np.int32)}, "'R'"),
        ({"normal.R": np.zeros((H, W, 3), np.float32)}, "'normal.R'"),
        ({"R": np.zeros((H, W), np.float32), "depth.Z": np.zeros((W, H), np.float32)}, "'depth.Z'"),
    ],
)
def test_write_rejects_bad_arrays(tmp_path, channels, needle):
    path = tmp_path / "bad.exr"
    with pytest.raises(DataError) as excinfo:
        write_exr(path, channels)
    one_line_error(excinfo, "bad.exr", needle)
    assert list(tmp_path.iterdir()) == []


def test_write_rejects_lossy_compression(tmp_path):
    with pytest.raises(DataError) as excinfo:
        write_exr(tmp_path / "x.exr", {"R": np.zeros((H, W), np.float32)}, compression="pxr24")
    one_line_error(excinfo, "x.exr", "pxr24")


def test_failed_write_keeps_previous_file_and_leaves_no_temp(tmp_path, monkeypatch):
    path = tmp_path / "img.exr"
    write_exr(path, {"R": np.ones((H, W), np.float32)})
    before = path.read_bytes()
    assert _tmp_leftovers(tmp_path) == []

    class HalfWriter:
        """Stands in for OpenEXR.File: writes a partial file, then fails like a full disk would."""

        def __init__(self, header, channels):
            pass

        def write(self, filename):
            with open(filename, "wb") as f:
                f.write(before[:20])
            raise RuntimeError("No space left on device")

    monkeypatch.setattr(exr.OpenEXR, "File", HalfWriter)
    with pytest.raises(DataError) as excinfo:
        write_exr(path, {"R": np.zeros((H, W), np.float32)})
    one_line_error(excinfo, "img.exr", "No space left")
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert _tmp_leftovers(tmp_path) == []
    np.testing.assert_array_equal(read_exr(path)["R"], 1.0)


def test_atomic_path_helpers(tmp_path):
    target = tmp_path / "sub" / "dir" / "out.json"
    with atomic_path(target) as tmp:
        assert tmp.parent == target.parent and tmp.suffix == ".json" and tmp.name.startswith(".out.json.tmp-")
        tmp.write_text("{}")
        assert not target.exists()
    assert target.read_text() == "{}"

    with pytest.raises(ZeroDivisionError), atomic_path(target) as tmp:
        tmp.write_text("half")
        1 / 0  # noqa: B018
    assert target.read_text() == "{}"
    assert _tmp_leftovers(target.parent) == []

    atomic_write_text(target, "tëxt")
    assert target.read_text(encoding="utf-8") == "tëxt"
    atomic_write_bytes(target, b"\x00\x01")
    assert target.read_bytes() == b"\x00\x01"
    assert sorted(p.name for p in target.parent.iterdir()) == ["out.json"]


def test_read_missing_file(tmp_path):
    path = tmp_path / "nothere.exr"
    for call in (read_exr, exr_channel_names, exr_size):
        with pytest.raises(DataError) as excinfo:
            call(path)
        one_line_error(excinfo, "nothere.exr", "not found")


def test_read_missing_channels_names_them_and_what_was_found(tmp_path):
    path = tmp_path / "rgb.exr"
    write_exr(path, {c: np.zeros((H, W), np.float32) for c in "RGB"})
    with pytest.raises(DataError) as excinfo:
        read_exr(path, ["R", "diffuse.G", "depth.Z"])
    msg = one_line_error(excinfo, "rgb.exr", "'diffuse.G'", "'depth.Z'", "found: B, G, R")
    assert "'R'" not in msg.split("found")[0]


def test_missing_channel_message_stays_one_line_with_many_channels(tmp_path):
    path = tmp_path / "many.exr"
    write_exr(path, {f"aov{i:03d}.Z": np.zeros((H, W), np.float32) for i in range(200)})
    with pytest.raises(DataError) as excinfo:
        read_exr(path, ["R"])
    msg = one_line_error(excinfo, "many.exr", "'R'", "more")
    assert len(msg) < 2000


def test_read_corrupt_and_truncated_files(tmp_path):
    garbage = tmp_path / "garbage.exr"
    garbage.write_bytes(b"this is not an EXR file" * 10)
    good = tmp_path / "good.exr"
    write_exr(good, {"R": _values(np.random.default_rng(3), np.float32)})
    truncated = tmp_path / "truncated.exr"
    truncated.write_bytes(good.read_bytes()[: good.stat().st_size // 2])
    for path in (garbage, truncated):
        with pytest.raises(DataError) as excinfo:
            read_exr(path)
        one_line_error(excinfo, path.name)
    with pytest.raises(DataError) as excinfo:
        exr_channel_names(garbage)
    one_line_error(excinfo, "garbage.exr")


def test_openexr_groups_rgb_unless_separated(tmp_path):
    """Documents the library behaviour our reader works around (fails loudly if the API changes)."""
    path = tmp_path / "g.exr"
    write_exr(
        path,
        {c: np.zeros((H, W), np.float32) for c in ("R", "G", "B", "diffuse.R", "diffuse.G", "diffuse.B")},
    )
    assert set(OpenEXR.File(str(path)).channels()) == {"RGB", "diffuse"}
