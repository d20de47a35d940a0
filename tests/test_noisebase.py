"""Noisebase sample sets (issue 35): the reader against known samples of tiny stores written by the
independent fixture writer (tests/noisebase_fixture.py), against the `noisebase` package's own loaders on
the same files, and its one-line errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from src.data.noisebase import (
    Frame,
    forward_flow,
    ladder_color,
    pixel_moments,
    read_frames,
    volume_frame_buffers,
    volume_reference_buffers,
)
from src.errors import DataError
from tests.conftest import one_line_error
from tests.noisebase_fixture import (
    package_test_loader,
    package_training_loader,
    write_test_sequence,
    write_training_sequence,
)

BUFFERS = ["w_normal", "w_position", "diffuse", "color", "reference", "depth", "motion"]


@pytest.fixture(scope="module")
def training(tmp_path_factory):
    root = tmp_path_factory.mktemp("nb")
    data = write_training_sequence(root / "train" / "scene0000.zip", frames=3, size=16, spp=4, seed=1)
    return root, data


def _moments(samples, n):
    x = samples[..., :n].astype(np.float64)
    mean = x.mean(-1)
    var = ((x - mean[..., None]) ** 2).sum(-1) / (n - 1) / n
    return np.moveaxis(mean, 0, -1), var.mean(0)[..., None]


@pytest.mark.parametrize("n", [2, 4])
def test_pixel_means_and_variances_are_those_of_the_fixture_samples(training, n):
    root, data = training
    crop = [2, 3, 10, 12]
    (frame,) = read_frames(root / "train" / "scene0000.zip", "training", [1], n, crop, rendering=(64, 96))
    win = (slice(None), slice(2, 12), slice(3, 15))
    buffers = volume_frame_buffers(frame, None, n)
    for ours, known in (
        ("color", data["radiance"][1]),
        ("albedo", data["diffuse"][1].astype(np.float64)),
        ("normal", data["normal"][1].astype(np.float64)),
        ("position", data["position"][1]),
    ):
        mean, var = _moments(known[win], n)
        np.testing.assert_allclose(buffers[ours], mean, rtol=1e-5, atol=1e-6, err_msg=ours)
        np.testing.assert_allclose(buffers[f"{ours}Variance"], var, rtol=1e-4, atol=1e-9, err_msg=ours)
    distance = np.linalg.norm(
        data["position"][1][win] - data["camera_position"][1][:, None, None, None], axis=0
    )
    mean, var = _moments(distance[None], n)
    np.testing.assert_allclose(buffers["depth"], mean, rtol=1e-5)
    np.testing.assert_allclose(buffers["depthVariance"], var, rtol=1e-4, atol=1e-12)
    np.testing.assert_array_equal(buffers["surface"], buffers["color"])
    assert not buffers["volume"].any() and not buffers["sigma_t"].any()
    ref = volume_reference_buffers(frame, None)
    np.testing.assert_array_equal(ref["color"], np.moveaxis(data["reference"][1][:, 2:12, 3:15], 0, -1))
    assert not ref["colorVariance"].any()


def test_pixel_moments_needs_two_samples():
    with pytest.raises(DataError) as e:
        pixel_moments(np.zeros((3, 2, 2, 4)), 1)
    one_line_error(e, "dataset.noisy_spp", "at least 2")


def _pixels(points, vp, height, width):
    """(row, column) of world points (3, H, W) in a camera frame, written out from the format's docs."""
    clip = np.einsum("chw,cj->jhw", np.concatenate([points, np.ones((1, *points.shape[1:]))]), vp)
    x, y = clip[0] / clip[3], clip[1] / clip[3]
    return np.stack([(1 - y) * height / 2, (x + 1) * width / 2])


def test_forward_flow_follows_the_mean_position_into_the_next_moving_crop(training):
    root, data = training
    frames = read_frames(root / "train" / "scene0000.zip", "training", [0, 1], 4, rendering=(64, 96))
    buffers = volume_frame_buffers(frames[0], frames[1], 4)
    mean = data["position"][0].astype(np.float64).mean(-1)
    now = (
        _pixels(mean, data["view_proj_mat"][0].astype(np.float64), 64, 96)
        - data["crop_offset"][0][:, None, None]
    )
    then = (
        _pixels(mean, data["view_proj_mat"][1].astype(np.float64), 64, 96)
        - data["crop_offset"][1][:, None, None]
    )
    flow = then - now
    np.testing.assert_allclose(buffers["motion"][..., 0], flow[1], atol=2e-3)  # x: columns
    np.testing.assert_allclose(buffers["motion"][..., 1], flow[0], atol=2e-3)  # y: rows
    assert np.abs(flow).max() > 1.0  # the camera and the crop move: a zero flow would not pass
    last = volume_frame_buffers(frames[1], None, 4)
    assert not last["motion"].any()


def test_flow_is_zero_where_the_point_is_behind_a_camera(training):
    root, _ = training
    frames = read_frames(root / "train" / "scene0000.zip", "training", [0, 1], 4, rendering=(64, 96))
    behind = 2 * frames[0].camera_position - 0.0  # beyond the camera, away from the origin it looks at
    position = np.broadcast_to(behind, (4, 4, 3)).copy()
    assert not forward_flow(position, frames[0], frames[1]).any()


def test_a_point_on_a_coordinate_plane_has_flow_and_only_the_origin_means_no_surface(training):
    """Undefined is a pixel whose mean position is exactly 0 (no surface: sky samples read as 0), not one
    with a single coordinate 0: a point on the plane x = 0, y = 0 or z = 0 moves like any other."""
    root, data = training
    frames = read_frames(root / "train" / "scene0000.zip", "training", [0, 1], 4, rendering=(64, 96))
    mean = data["position"][0].astype(np.float64).mean(-1)  # (3, H, W)
    for axis in range(3):
        mean[axis, 0, axis] = 0.0  # pixel (0, axis) on the plane of that axis
    mean[:, 1, 1] = 0.0  # pixel (1, 1): no surface
    flow = forward_flow(np.moveaxis(mean, 0, -1), frames[0], frames[1])
    offsets = data["crop_offset"].astype(np.float64)
    then = _pixels(mean, data["view_proj_mat"][1].astype(np.float64), 64, 96) - offsets[1][:, None, None]
    now = _pixels(mean, data["view_proj_mat"][0].astype(np.float64), 64, 96) - offsets[0][:, None, None]
    want = np.moveaxis((then - now)[::-1], 0, -1)  # (H, W, 2): x, y
    for axis in range(3):
        np.testing.assert_allclose(flow[0, axis], want[0, axis], atol=2e-3, err_msg=str(axis))
        assert np.abs(flow[0, axis]).max() > 0.1
    assert not flow[1, 1].any()


def _frame(radiance: np.ndarray) -> Frame:
    """A frame holding only per-sample radiance (3, H, W, S) (what `pixel_moments`/`ladder_color` read)."""
    zeros = np.zeros_like(radiance)
    return Frame(radiance, zeros, zeros, zeros, radiance[..., 0], np.zeros(3), np.eye(4), np.zeros(2), (1, 1))


def test_non_finite_samples_count_as_zero_and_the_buffers_are_float32():
    samples = np.array([1.0, np.inf, -np.inf, np.nan, 3.0, np.inf], np.float32).reshape(1, 1, 1, 6)[..., :5]
    samples = samples.repeat(3, 0)
    mean, variance = pixel_moments(samples, 5)
    assert mean.dtype == variance.dtype == np.float32
    np.testing.assert_allclose(mean[0, 0], 0.8)  # (1 + 0 + 0 + 0 + 3) / 5
    np.testing.assert_allclose(variance[0, 0, 0], np.var([1, 0, 0, 0, 3], ddof=1) / 5, rtol=1e-6)
    rung = ladder_color(_frame(samples), 3)  # the last three: -inf, nan, 3 -> 0, 0, 3
    assert rung.dtype == np.float32 and rung.shape == (1, 1, 3)
    np.testing.assert_allclose(rung[0, 0], 1.0)
    tail = samples[..., [0, 1, 4]]  # the last three: 1, +inf, 3 -> 1, 0, 3
    np.testing.assert_allclose(ladder_color(_frame(tail), 3)[0, 0], 4.0 / 3.0)


def test_every_buffer_of_a_frame_and_of_its_reference_is_float32_and_the_reference_has_the_motion(training):
    root, _ = training
    frames = read_frames(root / "train" / "scene0000.zip", "training", [0, 1], 4, rendering=(64, 96))
    noisy = volume_frame_buffers(frames[0], frames[1], 4)
    reference = volume_reference_buffers(frames[0], frames[1])
    for buffers in (noisy, reference):
        assert {name: a.dtype for name, a in buffers.items()} == dict.fromkeys(buffers, np.dtype(np.float32))
    np.testing.assert_array_equal(reference["motion"], noisy["motion"])  # the flow into the next frame
    for name in ("albedo", "albedoVariance", "normalVariance", "depth", "depthVariance"):  # all 4 samples
        np.testing.assert_array_equal(reference[name], noisy[name], err_msg=name)
    assert np.abs(reference["motion"]).max() > 1.0


def _point_at_depths(base: np.ndarray, now: Frame, then: Frame, w_now: float, w_then: float) -> np.ndarray:
    """A world point near `base` whose clip w is `w_now` in `now`'s camera and `w_then` in `then`'s (w is
    linear in the point: [p, 1] @ view_proj[:, 3])."""
    g = np.stack([now.view_proj[:3, 3], then.view_proj[:3, 3]])  # (2, 3): the gradients of the two w's
    w0 = np.array([base @ g[0] + now.view_proj[3, 3], base @ g[1] + then.view_proj[3, 3]])
    step = np.linalg.solve(g @ g.T, np.array([w_now, w_then]) - w0)
    return base + step @ g


def test_flow_is_defined_in_front_of_both_cameras_at_any_depth_and_zero_behind_either(training):
    root, data = training
    frames = read_frames(root / "train" / "scene0000.zip", "training", [0, 1], 4, rendering=(64, 96))
    base = data["position"][0].astype(np.float64).mean(-1)[:, 4, 4]
    depths = [
        [(0.5, 0.5), (3.0, -1.0)],
        [(-1.0, 3.0), (0.0, 3.0)],
    ]  # near both; behind next; behind; on plane
    points = np.array([[_point_at_depths(base, frames[0], frames[1], *d) for d in row] for row in depths])
    flow = forward_flow(points, frames[0], frames[1])
    offsets = data["crop_offset"].astype(np.float64)
    grid = np.moveaxis(points, -1, 0)
    then = _pixels(grid, data["view_proj_mat"][1].astype(np.float64), 64, 96) - offsets[1][:, None, None]
    now = _pixels(grid, data["view_proj_mat"][0].astype(np.float64), 64, 96) - offsets[0][:, None, None]
    for i, j in ((0, 0), (1, 1)):  # depths below 1 in one camera: defined all the same
        np.testing.assert_allclose(flow[i, j], (then - now)[::-1, i, j], rtol=1e-4)
        assert np.abs(flow[i, j]).max() > 0.1
    assert not flow[0, 1].any() and not flow[1, 0].any()  # behind the next camera; behind this one


@pytest.mark.parametrize(
    ("crop", "ok"),
    [
        ([0, 0, 1, 1], True),  # one pixel
        ([4, 6, 12, 10], True),  # to the last row and column of the 16 x 16 frame
        ([5, 6, 12, 10], False),  # one row past the bottom
        ([4, 7, 12, 10], False),  # one column past the right
        ([0, 0, 0, 4], False),
        ([0, 0, 4, 0], False),
        ([-1, 0, 4, 4], False),
        ([0, -1, 4, 4], False),
    ],
)
def test_a_window_may_reach_each_edge_of_the_frame_and_no_further(training, crop, ok):
    root, data = training
    path = root / "train" / "scene0000.zip"
    if ok:
        (frame,) = read_frames(path, "training", [0], 2, crop, rendering=(64, 96))
        top, left, h, w = crop
        np.testing.assert_array_equal(
            frame.reference, data["reference"][0][:, top : top + h, left : left + w]
        )
        return
    with pytest.raises(DataError) as e:
        read_frames(path, "training", [0], 2, crop, rendering=(64, 96))
    one_line_error(e, f"dataset.crop={crop}", "16x16")


def test_a_colour_array_of_the_wrong_rank_names_the_formats_layout(tmp_path):
    for fmt, want in (("training", "[F, 4, H, W, S]"), ("test", "[4, H, W, S]")):
        wrong = np.zeros((4, 2, 2, 2, 2, 1) if fmt == "test" else (4, 2, 2, 2), np.uint8)
        path = tmp_path / fmt / "scene0000.zip"
        write_training_sequence(path, frames=1, size=4, spp=2, replace={"color": wrong})
        with pytest.raises(DataError) as e:
            read_frames(path, fmt, [0], 2)
        one_line_error(e, str(path), f"expected {want} ({fmt})")


def test_a_test_store_has_one_frame():
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        write_test_sequence(Path(tmp), "kitchen", frames=1, height=12, width=10, spp=4)
        path = Path(tmp) / "kitchen" / "frame0000.zip"
        assert len(read_frames(path, "test", [0], 4)) == 1
        with pytest.raises(DataError) as e:
            read_frames(path, "test", [1], 4)
        one_line_error(e, str(path), "has 1 frames", "[1]")


def test_a_training_store_rebuilds_its_view_projection_and_ignores_the_stored_one(tmp_path):
    """The training loader rebuilds `view_proj_mat` from `proj_mat` and the camera vectors; a test store's
    is read as stored. A training store whose stored matrix is garbage reads the same as a correct one."""
    good = write_training_sequence(tmp_path / "good" / "scene0000.zip", frames=2, size=8, spp=2, seed=3)
    garbage = {"view_proj_mat": np.full_like(good["view_proj_mat"], 7.0)}
    write_training_sequence(
        tmp_path / "bad" / "scene0000.zip", frames=2, size=8, spp=2, seed=3, replace=garbage
    )
    read = [
        read_frames(tmp_path / d / "scene0000.zip", "training", [0, 1], 2, rendering=(64, 96))
        for d in ("good", "bad")
    ]
    for f in (0, 1):
        np.testing.assert_array_equal(read[0][f].view_proj, read[1][f].view_proj)
        np.testing.assert_allclose(read[0][f].view_proj, good["view_proj_mat"][f], rtol=1e-5, atol=1e-6)


def test_our_samples_equal_the_package_training_loader(training):

    root, _ = training
    theirs = package_training_loader(root, 3, 16, (64, 96), 3, BUFFERS)[{"idx": 2, "epoch": 0}]
    (ours,) = read_frames(root / "train" / "scene0000.zip", "training", [2], 3, rendering=(64, 96))
    np.testing.assert_array_equal(ours.radiance, theirs["color"])
    np.testing.assert_array_equal(ours.position, theirs["w_position"])
    np.testing.assert_array_equal(ours.normal, theirs["w_normal"])
    np.testing.assert_array_equal(ours.diffuse, theirs["diffuse"])
    np.testing.assert_array_equal(ours.reference, theirs["reference"])
    np.testing.assert_array_equal(ours.view_proj, theirs["view_proj_mat"])
    np.testing.assert_array_equal(ours.offset, theirs["crop_offset"])
    # their log depth is of our per-sample distance
    distance = np.linalg.norm(ours.position - ours.camera_position[:, None, None, None], axis=0)
    np.testing.assert_allclose(np.log(1 + 1 / distance), theirs["depth"][0], rtol=1e-5)


def test_our_samples_equal_the_package_test_loader_on_its_rows(tmp_path):

    data = write_test_sequence(tmp_path / "test8", "bistro1", frames=2, height=72, width=16, spp=4, seed=2)
    theirs = package_test_loader(tmp_path, "bistro1", 2, (72, 16), 4, BUFFERS)[1]
    # the package keeps rows 28:-28 of a test frame; our window [28, 0, 16, 16] is those rows
    (ours,) = read_frames(tmp_path / "test8" / "bistro1" / "frame0001.zip", "test", [0], 4, [28, 0, 16, 16])
    np.testing.assert_array_equal(ours.radiance, theirs["color"])
    np.testing.assert_array_equal(ours.position, theirs["w_position"])
    np.testing.assert_array_equal(ours.normal, theirs["w_normal"])
    np.testing.assert_array_equal(ours.reference, theirs["reference"])
    np.testing.assert_array_equal(ours.view_proj, data["view_proj_mat"][1])
    np.testing.assert_allclose(ours.radiance, data["radiance"][1][:, 28:44], rtol=1e-6)
    assert ours.rendering == (72, 16) and list(ours.offset) == [28, 0]


@pytest.mark.parametrize(
    ("skip", "replace", "needles"),
    [
        (("normal",), None, ["'normal'", "missing"]),
        (
            (),
            {"diffuse": np.zeros((3, 3, 16, 16, 4), np.float16)},
            ["'diffuse'", "(3, 3, 16, 16, 4)", "expected (2, 3, 16, 16, 4)"],
        ),
        (
            (),
            {"normal": np.zeros((2, 3, 16, 16, 4), np.float32)},
            ["'normal'", "float32", "expected float16"],
        ),
        ((), {"exposure": np.zeros((2, 3), np.float32)}, ["'exposure'", "(2, 3)", "expected (2, 2)"]),
    ],
)
def test_a_bad_array_is_one_line_naming_file_and_array(tmp_path, skip, replace, needles):
    path = tmp_path / "scene0000.zip"
    write_training_sequence(path, frames=2, skip=skip, replace=replace)
    with pytest.raises(DataError) as e:
        read_frames(path, "training", [0, 1], 4, rendering=(64, 96))
    one_line_error(e, str(path), *needles)


def test_a_missing_or_corrupt_store_is_one_line(tmp_path):
    with pytest.raises(DataError) as e:
        read_frames(tmp_path / "scene0007.zip", "training", [0], 4)
    one_line_error(e, "scene0007.zip", "no such Noisebase ZipStore")
    bad = tmp_path / "scene0008.zip"
    bad.write_bytes(b"not a zip at all")
    with pytest.raises(DataError) as e:
        read_frames(bad, "training", [0], 4)
    one_line_error(e, "scene0008.zip", "not a readable Zarr ZipStore")


def test_asking_for_more_frames_samples_or_window_than_stored_is_one_line(training):
    root, _ = training
    path = root / "train" / "scene0000.zip"
    for kwargs, needle in (
        ({"frames": [3]}, "has 3 frames"),
        ({"samples": 5}, "has 4 samples per pixel"),
        ({"crop": [8, 8, 9, 4]}, "dataset.crop"),
    ):
        args = {"frames": [0], "samples": 4, "crop": None} | kwargs
        with pytest.raises(DataError) as e:
            read_frames(path, "training", args["frames"], args["samples"], args["crop"], rendering=(64, 96))
        one_line_error(e, str(path), needle)


# Mutation testing (scripts/mutation.sh noisebase_data), src/data/noisebase.py: the mutants left alive are
# equivalent:
# - dtypes dropped or None where the value is float32 already (the store's positions, the flow's zeros)
#   or becomes float32 on the way out (the EXR writer), and `nan=0.0` dropped (numpy's default);
# - `FlipRotate(7, ...)` with another rendering size or crop offset: orientation 7 (no flip, no rotation)
#   reads neither; `slice(None, n)` / `slice(n)` for `slice(0, n)`; `np.einsum` subscripts upper-cased;
# - the flow's `isfinite` taken over the whole frame, and `w <= 0` against `w < 0`: a flow is non-finite
#   only where a w is exactly 0, which the w rule already catches;
# - the conversion record's key names and the summary's "sequences"/"seconds" keys (the record compares
#   with itself; the summary is printed), `raw.mkdir(parents=...)` (the data folder exists), `same = None`,
#   a stamp without the store's path (the paths are in the record's settings too);
# - `slice(0, None)` for a window of the whole frame;
# - the error texts of a wrong colour rank other than the format's layout (read by a person, and
#   `test_a_colour_array_of_the_wrong_rank_names_the_formats_layout` reads the layout).
