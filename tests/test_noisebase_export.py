"""Writing Noisebase sample sets (issue 35): the RGBE encoder against the package's own, its error bound,
and round trips of exported training and test sets through the `noisebase` package's loaders (and ours)."""

from __future__ import annotations

import numpy as np
import pytest

from src.data.noisebase import read_frames
from src.data.noisebase_export import (
    FAR,
    NEAR,
    encode_rgbe,
    frame_arrays,
    projection_matrix,
    write_test_frame,
    write_training_sequence,
)
from src.errors import DataError
from tests.conftest import one_line_error
from tests.noisebase_fixture import package_test_loader, package_training_loader

BUFFERS = ["w_normal", "w_position", "w_motion", "diffuse", "color", "reference"]


def _radiance(rng, shape=(3, 6, 5, 4)):
    return np.exp(rng.normal(0, 1.5, shape))  # positive, a few stops of range


def test_the_rgbe_bytes_are_the_packages_for_the_same_dither():
    from noisebase.compression import compress_RGBE

    color = _radiance(np.random.default_rng(0))
    np.random.seed(5)  # noqa: NPY002 (the package draws its dither from numpy's global generator)
    theirs, (lo, hi) = compress_RGBE(color)
    ours, exposure = encode_rgbe(color, np.random.RandomState(5).random_sample)
    np.testing.assert_array_equal(ours, theirs)
    np.testing.assert_allclose(exposure, [lo, hi], rtol=1e-6)


def test_a_decoded_channel_is_within_one_step_of_its_exponent_and_unbiased():
    from noisebase.compression import decompress_RGBE

    rng = np.random.default_rng(1)
    color = _radiance(rng)
    color[0, 0, 0, 0] = 0.0  # a black channel stays 0
    color[:, 1, 1, 1] = 0.0  # a black sample
    rgbe, exposure = encode_rgbe(color, rng.random)
    decoded = decompress_RGBE(rgbe, exposure)
    step = np.exp((rgbe[3].astype(np.float64) + 1) / 256 * (exposure[1] - exposure[0]) + exposure[0]) / 255
    assert (np.abs(decoded - color) <= step * (1 + 1e-5)).all()
    assert decoded[0, 0, 0, 0] == 0 and not decoded[:, 1, 1, 1].any()
    # the dither makes a byte unbiased: the mean of many encodings is the value, far within one step
    many = np.mean([decompress_RGBE(*encode_rgbe(color, rng.random)) for _ in range(400)], axis=0)
    assert (np.abs(many - color) < 0.2 * step).mean() > 0.95
    plain = np.floor(color / (step * 255) * 255) * step  # no dither: biased low by half a step on average
    assert np.abs(many - color).mean() < 0.5 * np.abs(plain - color).mean()


def test_an_all_black_frame_encodes_to_zero_and_bad_radiance_is_one_line():
    rgbe, exposure = encode_rgbe(np.zeros((3, 2, 2, 2)), np.random.default_rng(0).random)
    assert not rgbe.any() and not exposure.any()
    assert (rgbe.shape, rgbe.dtype, exposure.shape, exposure.dtype) == (
        (4, 2, 2, 2),
        np.uint8,
        (2,),
        np.float32,
    )
    with pytest.raises(DataError) as e:
        encode_rgbe(np.full((3, 1, 1, 2), np.nan), np.random.default_rng(0).random)
    one_line_error(e, "finite and non-negative")


def test_black_samples_and_channels_encode_as_the_packages():
    from noisebase.compression import compress_RGBE

    color = _radiance(np.random.default_rng(2))
    color[:, 1, 1, :2] = 0.0  # black samples: every byte 0, the exponent too
    color[1:, 2, 2, 0] = 0.0  # a pure red sample: its green and blue bytes stay 0
    np.random.seed(9)  # noqa: NPY002 (the package's global generator)
    theirs, _ = compress_RGBE(color)
    ours, _ = encode_rgbe(color, np.random.RandomState(9).random_sample)
    np.testing.assert_array_equal(ours, theirs)
    assert not ours[:, 1, 1, :2].any()
    # no dither at all: an exact zero channel never rounds up (only a positive fraction above the draw does)
    zero_dither, _ = encode_rgbe(color, np.zeros)
    assert not zero_dither[1:3, 2, 2, 0].any() and zero_dither[0, 2, 2, 0] > 0


def test_a_frame_of_one_value_gets_a_tiny_range_and_decodes_to_it():
    from noisebase.compression import decompress_RGBE

    rgbe, exposure = encode_rgbe(np.full((3, 2, 2, 2), 2.0), np.random.default_rng(0).random)
    assert exposure[0] == pytest.approx(np.log(2.0)) and exposure[1] - exposure[0] == pytest.approx(
        1e-6, rel=0.1
    )
    np.testing.assert_allclose(decompress_RGBE(rgbe, exposure), 2.0, rtol=0.01)


def test_the_projection_maps_the_near_plane_to_0_the_far_plane_to_1_and_the_field_of_view_to_the_edges():
    p = projection_matrix(90.0, 200, 100).astype(np.float64)
    assert projection_matrix(90.0, 200, 100).dtype == np.float32

    def ndc(x, y, z):
        clip = p @ np.array([x, y, z, 1.0])
        return clip[:3] / clip[3]

    np.testing.assert_allclose(ndc(0, 0, NEAR), [0, 0, 0], atol=1e-6)
    np.testing.assert_allclose(ndc(0, 0, FAR), [0, 0, 1], atol=1e-6)
    np.testing.assert_allclose(ndc(5.0, 0, 5.0), [1, 0, ndc(0, 0, 5.0)[2]], atol=1e-6)  # 45 deg: right edge
    np.testing.assert_allclose(ndc(0, 2.5, 5.0)[1:], [1.0, ndc(0, 0, 5.0)[2]], atol=1e-6)  # top edge
    np.testing.assert_allclose(p[3], [0, 0, 1, 0])  # w = z


def _frames(rng, frames, height, width, spp):
    out = []
    for f in range(frames):
        shape = (3, height, width, spp)
        normal = rng.normal(size=shape)
        samples = {
            "radiance": _radiance(rng, shape),
            "position": rng.uniform(-1, 1, shape),
            "motion": rng.uniform(-0.1, 0.1, shape),
            "normal": normal / np.linalg.norm(normal, axis=0),
            "diffuse": rng.uniform(0, 1, shape),
        }
        camera = {
            "camera_position": np.array([np.sin(0.1 * f) * 4, 1.0, np.cos(0.1 * f) * 4]),
            "camera_target": np.zeros(3),
            "camera_up": np.array([0.0, 1.0, 0.0]),
            "proj_mat": projection_matrix(40.0, 96, 64),
        }
        out.append((samples, rng.uniform(0, 2, shape[:3]), camera))
    return out


def _check_sample_buffers(theirs, samples, arrays):
    np.testing.assert_array_equal(theirs["w_position"], samples["position"].astype(np.float32))
    np.testing.assert_array_equal(theirs["w_normal"], samples["normal"].astype(np.float16).astype(np.float32))
    np.testing.assert_array_equal(theirs["diffuse"], samples["diffuse"].astype(np.float16).astype(np.float32))
    lo, hi = arrays["exposure"]
    step = np.exp((arrays["color"][3].astype(np.float64) + 1) / 256 * (hi - lo) + lo) / 255
    assert (np.abs(theirs["color"] - samples["radiance"]) <= step * (1 + 1e-5)).all()


def test_an_exported_training_sequence_reads_back_through_the_package_loader(tmp_path):

    rng = np.random.default_rng(2)
    made = _frames(rng, 2, 8, 8, 4)
    arrays = [
        frame_arrays(s, r, c, [10 + f, 20 + 3 * f], (64, 96), rng.random) for f, (s, r, c) in enumerate(made)
    ]
    write_training_sequence(tmp_path / "train" / "scene0000.zip", arrays)
    ds = package_training_loader(tmp_path, 2, 8, (64, 96), 4, BUFFERS)
    for f in range(2):
        theirs = ds[{"idx": f, "epoch": 0}]
        samples, reference, _ = made[f]
        _check_sample_buffers(theirs, samples, arrays[f])
        np.testing.assert_array_equal(theirs["reference"], reference.astype(np.float32))
        np.testing.assert_array_equal(theirs["view_proj_mat"], arrays[f]["view_proj_mat"])
        assert list(theirs["crop_offset"]) == [10 + f, 20 + 3 * f]
        if f:  # the stored world motion of the second frame comes back
            np.testing.assert_array_equal(theirs["w_motion"], samples["motion"].astype(np.float32))
    # ours and theirs agree on the same file
    (ours,) = read_frames(tmp_path / "train" / "scene0000.zip", "training", [1], 4, rendering=(64, 96))
    np.testing.assert_array_equal(ours.radiance, ds[{"idx": 1, "epoch": 0}]["color"])


def test_an_exported_test_sequence_reads_back_through_the_package_loader(tmp_path):

    rng = np.random.default_rng(3)
    made = _frames(rng, 2, 64, 8, 2)
    arrays = [frame_arrays(s, r, c, [0, 0], (64, 8), rng.random) for s, r, c in made]
    for f, a in enumerate(arrays):
        write_test_frame(tmp_path / "test8" / "seq" / f"frame{f:04d}.zip", a)
    ds = package_test_loader(tmp_path, "seq", 2, (64, 8), 2, BUFFERS)
    rows = slice(28, -28)  # the package's fixed crop of a test frame
    theirs = ds[1]
    samples, reference, _ = made[1]
    cropped = {k: v[:, rows] for k, v in samples.items()}
    _check_sample_buffers(
        theirs, cropped, {"exposure": arrays[1]["exposure"], "color": arrays[1]["color"][:, rows]}
    )
    np.testing.assert_array_equal(theirs["reference"], reference[:, rows].astype(np.float32))
    np.testing.assert_array_equal(theirs["view_proj_mat"], arrays[1]["view_proj_mat"])
    (ours,) = read_frames(tmp_path / "test8" / "seq" / "frame0001.zip", "test", [0], 2, [28, 0, 8, 8])
    np.testing.assert_array_equal(ours.radiance, theirs["color"])


def test_stores_are_lz4hc_9_chunked_per_frame_and_per_4_samples(tmp_path):
    """The layout the format page gives (docs/noisebase.md): Blosc LZ4HC level 9 with byte shuffle; a
    training store chunked one frame at a time, every per-sample array also per 4 samples."""
    import zarr
    from numcodecs import Blosc

    rng = np.random.default_rng(6)
    frames = [frame_arrays(*f, [0, 0], (4, 6), rng.random) for f in _frames(rng, 2, 4, 6, 8)]
    write_training_sequence(tmp_path / "train.zip", frames)
    write_test_frame(tmp_path / "test.zip", frames[0])
    for name, frame_axis in (("train.zip", True), ("test.zip", False)):
        group = zarr.open_group(zarr.ZipStore(str(tmp_path / name), mode="r"), mode="r")
        lead = (1,) if frame_axis else ()
        assert group["color"].chunks == (*lead, 4, 4, 6, 4) and group["position"].chunks == (
            *lead,
            3,
            4,
            6,
            4,
        )
        assert group["reference"].chunks == (*lead, 3, 4, 6)  # no sample axis: whole frames
        assert group["exposure"].chunks == (*lead, 2)
        codec = group["color"].compressor
        assert (codec.cname, codec.clevel, codec.shuffle) == ("lz4hc", 9, Blosc.SHUFFLE)
        assert not (tmp_path / f"{name}.part").exists()


def test_a_mismatched_buffer_is_one_line():
    rng = np.random.default_rng(4)
    samples, reference, camera = _frames(rng, 1, 4, 4, 2)[0]
    four = dict(samples, radiance=np.concatenate([samples["radiance"], samples["radiance"][:1]]))
    with pytest.raises(DataError) as e:  # four colour channels, the rank right
        frame_arrays(four, reference, camera, [0, 0], (4, 4), rng.random)
    one_line_error(e, "radiance", "(4, 4, 4, 2)", "expected (3, H, W, S)")
    samples["normal"] = samples["normal"][..., :1]
    with pytest.raises(DataError) as e:
        frame_arrays(samples, reference, camera, [0, 0], (4, 4), rng.random)
    one_line_error(e, "normal", "(3, 4, 4, 1)", "expected (3, 4, 4, 2)")


def _volumetric_smoke():
    from omegaconf import OmegaConf

    from tests.conftest import compose_config

    cfg = compose_config(["dataset=volumetric", "profile=smoke"])
    return OmegaConf.to_container(cfg.dataset, resolve=True)


def test_an_exported_camera_projects_as_the_renderers_camera():
    """The Noisebase camera of a volumetric frame (position, target, up, projection -> the package's
    view-projection and pixel mapping) puts world points on the pixels nrbench's renderer does."""
    from noisebase.projective import screen_space_position

    from src.data.noisebase_export import view_projection
    from src.render.noisebase_export import noisebase_camera
    from src.render.volume_camera import project
    from src.render.volume_scenes import camera_at

    ds = _volumetric_smoke()
    w, h = int(ds["width"]), int(ds["height"])
    camera = camera_at("cloud", 0, 1, ds)
    pv = view_projection(noisebase_camera(camera, w, h), (h, w), h)
    rng = np.random.default_rng(0)
    ahead = camera.to_world[:3, 3] + camera.to_world[:3, 2] * 6  # points around the view direction
    points = ahead[:, None, None] + rng.normal(0, 1.0, (3, 4, 5))
    ij = screen_space_position(points[..., None].astype(np.float32), pv, h, w)[..., 0]
    xy, depth = project(np.moveaxis(points, 0, -1), camera, w, h)
    assert (depth > 0).all()
    np.testing.assert_allclose(ij[1], xy[..., 0], atol=2e-3)  # columns
    np.testing.assert_allclose(ij[0], xy[..., 1], atol=2e-3)  # rows
    assert np.ptp(xy[..., 0]) > 5  # the points spread over the frame


@pytest.mark.slow
def test_an_exported_volumetric_sequence_reads_back_with_its_renders(tmp_path, mitsuba_variant):
    """Render a smoke volumetric scene per sample, export it, read it back with the package's loader and
    ours: per-sample colour within the RGBE step of a 1-spp render with that sample's seed, the reference
    the volumetric dataset's own reference file, and our flow of the exported set the renderer's own motion
    (`frame_motion`) of the same mean positions."""

    from src.data.noisebase import volume_frame_buffers
    from src.render.noisebase_export import export_volumetric_sequences
    from src.render.render_dataset import scene_sources
    from src.render.volume_dataset import frame_motion
    from src.render.volume_scenes import camera_at

    ds = _volumetric_smoke() | {"width": 16, "height": 12, "noisy_spp": [2, 4], "reference_spp": 8}
    (path,) = export_volumetric_sequences(ds, tmp_path / "train", "training", 2, scenes=["fog_objects-0000"])
    theirs = package_training_loader(tmp_path, 2, 12, (12, 16), 2, BUFFERS)[{"idx": 0, "epoch": 0}]
    assert theirs["color"].shape == (3, 12, 16, 2) and theirs["color"].max() > 0
    assert not np.array_equal(theirs["color"][..., 0], theirs["color"][..., 1])  # distinct seeds
    frames = read_frames(path, "training", [0, 1], 2, rendering=(12, 16))
    np.testing.assert_array_equal(frames[0].radiance, theirs["color"])
    buffers = volume_frame_buffers(frames[0], frames[1], 2)
    (source,) = [s for s in scene_sources(ds) if s.name == "fog_objects-0000"]
    cameras = [camera_at(source.base, source.seed, f, ds) for f in (0, 1)]
    np.testing.assert_allclose(buffers["motion"], frame_motion(buffers["position"], *cameras), atol=5e-3)
    assert np.abs(buffers["motion"]).max() > 0.01

    import mitsuba as mi

    from src.data.volume_buffers import load_volume_exr
    from src.render.render_dataset import pass_seed
    from src.render.volume_dataset import INTEGRATOR, load_volume_frame, render_volumetric_dataset
    from src.render.volume_film import render_volume_buffers

    render_volumetric_dataset(ds, tmp_path / "raw", scenes=["fog_objects-0000"], frames=[0])
    reference, _ = load_volume_exr(tmp_path / "raw" / "fog_objects-0000-f0000-00008spp.exr")
    np.testing.assert_array_equal(theirs["reference"], np.moveaxis(reference["color"], -1, 0))
    integrator = mi.load_dict({"type": INTEGRATOR, **ds["integrator"]})
    seed = pass_seed(int(ds["seed"]), "fog_objects-0000", 1, "noisy", 1, 0)  # sample 1 of frame 0
    sample = render_volume_buffers(load_volume_frame(source, 0, ds), integrator, 1, [seed])
    want = np.moveaxis(sample["color"], -1, 0)
    got = theirs["color"][..., 1]
    import zarr

    lo, hi = zarr.open_group(zarr.ZipStore(str(path), mode="r"), mode="r")["exposure"][0]
    step = want.max(0) * np.exp((hi - lo) / 256) / 255  # a pixel's RGBE step: its exponent's, over 255
    assert (np.abs(got - want) <= step * (1 + 1e-4) + 1e-7).all()
    assert np.abs(got - want).mean() < 0.1 * np.abs(want).mean()


def test_a_pan_turns_the_camera_about_the_world_up_through_its_origin():
    from src.render.noisebase_export import panned

    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    to_world = np.eye(4)
    to_world[:3, :3], to_world[:3, 3] = q, [1.0, 2.0, 3.0]
    turned = panned(to_world, 30.0)
    np.testing.assert_array_equal(turned[:3, 3], to_world[:3, 3])
    np.testing.assert_allclose(turned[:3, :3].T @ turned[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(turned[1, :3], to_world[1, :3])  # heights of the axes kept
    for column in range(3):  # each axis turned by 30 degrees about +Y, counter-clockwise seen from above
        a, b = to_world[[0, 2], column], turned[[0, 2], column]
        if np.linalg.norm(a) > 1e-6:
            angle = np.degrees(np.arctan2(a[1] * b[0] - a[0] * b[1], a @ b))
            assert angle == pytest.approx(30.0)


@pytest.mark.slow
def test_an_exported_still_scene_pans_and_reads_back(tmp_path, mitsuba_variant):
    """A procedural still scene exported as a 2-frame panning sequence: the package loader reads it, and
    our flow of the exported set is the renderer's camera motion of the same mean positions."""
    from omegaconf import OmegaConf

    from src.data.noisebase import volume_frame_buffers
    from src.render.noisebase_export import export_still_sequences, panned
    from src.render.volume_camera import Camera, motion_vectors
    from tests.conftest import compose_config

    ds = OmegaConf.to_container(compose_config(["dataset=procedural", "profile=smoke"]).dataset, resolve=True)
    ds |= {"width": 16, "height": 12, "reference_spp": 8}
    (path,) = export_still_sequences(ds, tmp_path / "train", "training", 2, 2, 3.0, scenes=["tabletop-0000"])
    theirs = package_training_loader(tmp_path, 2, 12, (12, 16), 2, BUFFERS)[{"idx": 1, "epoch": 0}]
    assert theirs["color"].shape == (3, 12, 16, 2) and theirs["color"].max() > 0
    frames = read_frames(path, "training", [0, 1], 2, rendering=(12, 16))
    np.testing.assert_array_equal(frames[1].radiance, theirs["color"])
    buffers = volume_frame_buffers(frames[0], frames[1], 2)
    import mitsuba as mi

    from src.render.render_dataset import load_scene, scene_sources

    (source,) = [s for s in scene_sources(ds) if s.name == "tabletop-0000"]
    params = mi.traverse(load_scene(source, ds)[1])
    start, fov = (
        np.array(params["to_world"].matrix).reshape(4, 4),
        float(np.array(params["x_fov"]).ravel()[0]),
    )
    cameras = [Camera(panned(start, 3.0 * f), fov) for f in (0, 1)]
    want = motion_vectors(buffers["position"].astype(np.float64), *cameras, 16, 12)
    hit = np.isfinite(want).all(-1) & np.any(buffers["position"] != 0, -1)
    np.testing.assert_allclose(buffers["motion"][hit], want[hit], atol=5e-3)
    assert np.abs(buffers["motion"][hit]).max() > 0.2  # 3 degrees of a ~40 degree view over 16 px


# --- stage=export -------------------------------------------------------------------------------------


def test_export_refuses_data_it_cannot_render_and_a_bad_format_in_one_line(tmp_path):
    from src.errors import ConfigError
    from src.schema.run import validate_run
    from src.stages import export
    from tests.conftest import smoke_config

    cfg = smoke_config(tmp_path, tmp_path / "run", ["dataset=noisebase", f"dataset.root={tmp_path}"])
    with pytest.raises(ConfigError) as excinfo:
        export(cfg)
    one_line_error(excinfo, "dataset=noisebase", "stage=export", "dataset=volumetric")
    assert not (tmp_path / "noisebase").exists()
    cfg = smoke_config(tmp_path, tmp_path / "run", ["export.format=video"])
    with pytest.raises(ConfigError) as excinfo:
        validate_run(cfg)
    one_line_error(excinfo, "export.format", "video")


@pytest.mark.slow
def test_stage_export_writes_a_set_the_package_reads(tmp_path):
    """The documented command end to end: `python -m src.run stage=export dataset=volumetric ...`."""
    import subprocess
    import sys

    from tests.conftest import ROOT

    out = tmp_path / "set"
    command = [
        sys.executable, "-m", "src.run", "stage=export", "dataset=volumetric", "profile=smoke",
        "dataset.width=16", "dataset.height=12", "dataset.reference_spp=8", "dataset.noisy_spp=[2,4]",
        "export.spp=2", "export.scenes=[fog_objects-0000]", f"export.out_dir={out / 'train'}",
        f"paths.data={tmp_path / 'data'}", "tracking.enabled=false",
    ]  # fmt: skip
    result = subprocess.run(command, capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "export: 1 Noisebase training-format stores (2 spp)" in result.stdout
    frames = _volumetric_smoke()["frames"]
    loader = package_training_loader(out, frames, 12, (12, 16), 2, BUFFERS)
    theirs = loader[{"idx": frames - 1, "epoch": 0}]
    assert theirs["color"].shape == (3, 12, 16, 2) and np.isfinite(theirs["color"]).all()


# Mutation testing (scripts/mutation.sh noisebase_data), src/data/noisebase_export.py: the mutants left
# alive are equivalent:
# - dtypes dropped or None where the value is already that dtype (float64 radiance, float32 cameras);
# - `FlipRotate(7, ...)` with another rendering size, window or crop offset: orientation 7 reads none;
# - the byte ceiling 256 for 255: E >= the brightest channel, so no byte reaches 256 (tested against the
#   package's encoder); `np.log(np.where(lit, brightest, 2.0))`: the value of an unlit sample is masked;
# - the temporary name (".part") and the ZipStore's mode (the temporary is removed first), Blosc's
#   `shuffle` (its default is the byte shuffle), a test frame's `frame_axis=None` (falsy), the keys taken
#   from frame 1 rather than frame 0 (every frame has the same arrays);
# - `lit = brightest >= 0`: a black sample's exponent is then floor(-inf) cast to uint8, 0 on this
#   platform (the parity with the package covers black samples).
