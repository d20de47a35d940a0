"""The volumetric dataset as files: EXR layout, file naming, sequence grouping, the renderer (caching,
subsets, motion, colour split) and the render stage from the command line."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest
from omegaconf import OmegaConf

from src.errors import ConfigError, DataError
from tests.conftest import ROOT, cli_job, compose_config, one_line_error


@pytest.fixture(scope="module")
def ds():
    """A tiny volumetric dataset: one fog scene, 2 frames of 16x12, 2 spp and an 8-spp reference."""
    cfg = compose_config(["dataset=volumetric", "profile=smoke"])
    ds = OmegaConf.to_container(cfg.dataset, resolve=True)
    ds.update(width=16, height=12, frames=2, bases=["fog_objects"], scenes_per_base=1, grid_res=8)
    ds.update(noisy_spp=[2], reference_spp=8)
    return ds


@pytest.fixture(scope="module")
def rendered(tmp_path_factory, mitsuba_variant, ds):
    from src.render.volume_dataset import render_volumetric_dataset

    raw = tmp_path_factory.mktemp("volumetric") / "raw"
    return raw, render_volumetric_dataset(ds, raw, "auto")


# --- naming ------------------------------------------------------------------------------------------------


def test_file_names_round_trip():
    from src.data.volume_buffers import parse_volume_exr_name, volume_exr_name

    name = volume_exr_name("cloud-0000", 3, 16)
    assert name == "cloud-0000-f0003-00016spp.exr"
    assert parse_volume_exr_name(f"/some/dir/{name}") == ("cloud-0000", 3, 16)
    assert parse_volume_exr_name(volume_exr_name("smoke_tabletop-0012", 1234, 4096)) == (
        "smoke_tabletop-0012",
        1234,
        4096,
    )


@pytest.mark.parametrize(
    "bad", ["cloud-0000-00016spp.exr", "cloud-0000-f3-spp.exr", "cloud-0000-f0003-00000spp.exr", "x.exr"]
)
def test_bad_file_names_are_one_line_data_errors(bad):
    from src.data.volume_buffers import parse_volume_exr_name

    with pytest.raises(DataError) as err:
        parse_volume_exr_name(bad)
    one_line_error(err, bad, "f0003-00016spp.exr")


def _touch(folder, names):
    folder.mkdir(exist_ok=True)
    for name in names:
        (folder / name).write_bytes(b"")
    return folder


def test_grouping_into_sequences(tmp_path):
    from src.data.volume_buffers import group_volume_dataset, volume_exr_name

    names = [volume_exr_name(s, f, n) for s in ("b-0001", "a-0000") for f in (1, 0) for n in (64, 4)]
    groups = group_volume_dataset(_touch(tmp_path / "raw", names))
    assert list(groups) == ["a-0000", "b-0001"]
    assert list(groups["a-0000"]) == [0, 1]
    assert list(groups["a-0000"][1]) == [4, 64]
    assert groups["b-0001"][1][64].name == "b-0001-f0001-00064spp.exr"


@pytest.mark.parametrize(
    ("names", "needles"),
    [
        (
            ["a-f0000-00004spp.exr", "a-f0000-00064spp.exr", "a-f0002-00004spp.exr", "a-f0002-00064spp.exr"],
            ["'a'", "frame(s) [1]"],
        ),
        (
            ["a-f0000-00004spp.exr", "a-f0000-00064spp.exr", "a-f0001-00004spp.exr"],
            ["'a' frame 1", "[64]", "(the reference)"],
        ),
        (["a-f0000-00004spp.exr", "a-f0001-00004spp.exr"], ["'a'", "single sample count", "reference"]),
        (["a-0000-00004spp.exr"], ["a-0000-00004spp.exr"]),
        ([], ["no '<scene>-f<FFFF>-<NNNNN>spp.exr' files"]),
    ],
)
def test_incomplete_sequences_are_one_line_data_errors(tmp_path, names, needles):
    from src.data.volume_buffers import group_volume_dataset

    with pytest.raises(DataError) as err:
        group_volume_dataset(_touch(tmp_path / "raw", names))
    one_line_error(err, *needles)


# --- layout ------------------------------------------------------------------------------------------------


def test_layout_is_derived_from_the_integrators_buffers():
    from src.data.volume_aovs import CHANNEL_COUNT, MOMENT_BUFFERS
    from src.data.volume_buffers import VOLUME_LAYOUT

    buffers = VOLUME_LAYOUT.buffers
    assert buffers["color"] == ("R", "G", "B")
    for buf, n in CHANNEL_COUNT.items():
        assert len(buffers[buf]) == n
    assert buffers["depth"] == ("depth.Z",)
    assert buffers["position"] == ("position.X", "position.Y", "position.Z")
    assert buffers["transmittance"] == ("transmittance.R", "transmittance.G", "transmittance.B")
    assert buffers["motion"] == ("motion.X", "motion.Y")
    assert [b for b in buffers if b.endswith("Variance")] == [f"{b}Variance" for b in MOMENT_BUFFERS]
    assert all(buffers[f"{b}Variance"] == (f"{b}Variance.Z",) for b in MOMENT_BUFFERS)
    assert set(VOLUME_LAYOUT.radiance) == {"color", "surface", "volume", "volume_single", "volume_multi"}
    channels = [c for chans in buffers.values() for c in chans]
    assert len(channels) == len(set(channels))


def _random_buffers(h=5, w=7, seed=0):
    from src.data.volume_buffers import VOLUME_LAYOUT

    rng = np.random.default_rng(seed)
    return {b: rng.random((h, w, len(c)), dtype=np.float32) for b, c in VOLUME_LAYOUT.buffers.items()}


def test_write_load_round_trip_by_channel_name(tmp_path):
    from src.data.volume_buffers import load_volume_exr, write_volume_exr
    from src.io.exr import read_exr

    buffers = _random_buffers()
    path = write_volume_exr(tmp_path / "a-f0000-00004spp.exr", buffers)
    raw = read_exr(path)
    np.testing.assert_array_equal(raw["G"], buffers["color"][..., 1])
    np.testing.assert_array_equal(raw["position.Z"], buffers["position"][..., 2])
    np.testing.assert_array_equal(raw["motion.Y"], buffers["motion"][..., 1])
    np.testing.assert_array_equal(raw["volumeVariance.Z"], buffers["volumeVariance"][..., 0])
    loaded, report = load_volume_exr(path, expected_size=(5, 7))
    assert report.total == 0 and list(loaded) == list(buffers)
    for name, value in buffers.items():
        np.testing.assert_array_equal(loaded[name], value)


def test_loader_rejects_a_file_missing_a_buffer(tmp_path):
    from src.data.volume_buffers import load_volume_exr, write_volume_exr

    buffers = _random_buffers()
    del buffers["scatter_albedo"]
    path = write_volume_exr(tmp_path / "a-f0000-00004spp.exr", buffers)
    with pytest.raises(DataError) as err:
        load_volume_exr(path)
    one_line_error(err, str(path), "scatter_albedo.R", "missing")


# --- motion ------------------------------------------------------------------------------------------------


def test_frame_motion_conventions():
    from src.render.volume_camera import Camera, look_at, motion_vectors
    from src.render.volume_dataset import frame_motion

    cam_t = Camera(look_at([0.0, 1.0, 5.0], [0.0, 0.0, 0.0]), 40.0)
    cam_t1 = Camera(look_at([0.3, 1.0, 5.0], [0.0, 0.0, 0.0]), 40.0)
    rng = np.random.default_rng(1)
    position = rng.uniform(-1, 1, (6, 8, 3))
    position[0, 0] = 0.0  # no sample found a point
    position[0, 1] = [0.0, 0.0, 50.0]  # behind the camera: NaN flow
    flow = frame_motion(position, cam_t, cam_t1)
    assert flow.dtype == np.float32 and flow.shape == (6, 8, 2) and np.isfinite(flow).all()
    expected = motion_vectors(position, cam_t, cam_t1, 8, 6)
    assert np.isnan(expected[0, 1]).all()
    defined = np.isfinite(expected).all(-1)
    defined[0, 0] = False
    np.testing.assert_allclose(flow[defined], expected[defined], rtol=1e-5, atol=1e-5)
    assert (flow[~defined] == 0).all() and np.abs(flow[defined]).max() > 0.1
    np.testing.assert_array_equal(frame_motion(position, cam_t, None), np.zeros((6, 8, 2), np.float32))


# --- the renderer ------------------------------------------------------------------------------------------


def test_render_writes_every_frame_at_every_spp(rendered, ds):
    from src.data.volume_buffers import group_volume_dataset

    raw, summary = rendered
    groups = group_volume_dataset(raw)
    assert {s: {f: list(g) for f, g in frames.items()} for s, frames in groups.items()} == {
        "fog_objects-0000": {0: [2, 8], 1: [2, 8]}
    }
    assert summary["files_rendered"] == 4 and summary["files_cached"] == 0
    assert summary["samples"] == 2 * 16 * 12 * (2 + 8) and summary["samples_per_second"] > 0
    assert sorted(p.name for p in (raw / "manifest").iterdir()) == sorted(
        f"{p.name}.json" for p in raw.glob("*.exr")
    )


def test_rerun_renders_nothing(rendered, ds):
    from src.render.volume_dataset import render_volumetric_dataset

    raw, _ = rendered
    before = {p.name: p.stat().st_mtime_ns for p in raw.glob("*.exr")}
    summary = render_volumetric_dataset(ds, raw, "auto")
    assert summary["files_rendered"] == 0 and summary["files_cached"] == 4
    assert {p.name: p.stat().st_mtime_ns for p in raw.glob("*.exr")} == before


def test_files_hold_colour_split_motion_and_variances(rendered, ds):
    from src.data.volume_buffers import load_volume_exr
    from src.render.render_dataset import scene_sources
    from src.render.volume_dataset import frame_motion
    from src.render.volume_scenes import camera_at

    raw, _ = rendered
    source = scene_sources(ds)[0]
    cameras = [camera_at(source.base, source.seed, f, ds) for f in (0, 1)]
    for frame, spp in ((0, 2), (0, 8), (1, 8)):
        buffers, _ = load_volume_exr(
            raw / f"fog_objects-0000-f{frame:04d}-{spp:05d}spp.exr", expected_size=(12, 16)
        )
        np.testing.assert_allclose(
            buffers["color"], buffers["surface"] + buffers["volume"], rtol=1e-5, atol=1e-6
        )
        assert buffers["volume"].max() > 0  # the fog scatters light
        assert buffers["colorVariance"].shape == (12, 16, 1) and buffers["colorVariance"].max() > 0
        expected = frame_motion(buffers["position"], cameras[frame], cameras[1] if frame == 0 else None)
        np.testing.assert_array_equal(buffers["motion"], expected)
    assert np.abs(expected).max() == 0  # the last frame
    first, _ = load_volume_exr(raw / "fog_objects-0000-f0000-00008spp.exr")
    assert np.abs(first["motion"]).max() > 0


def test_subsets_compose_to_the_same_files(rendered, ds, tmp_path):
    from src.io.exr import read_exr
    from src.render.volume_dataset import render_volumetric_dataset

    full, _ = rendered
    raw = tmp_path / "raw"
    assert render_volumetric_dataset(ds, raw, "auto", frames=[1])["files_rendered"] == 2
    assert render_volumetric_dataset(ds, raw, "auto", scenes=["fog_objects-0000"])["files_rendered"] == 2
    assert sorted(p.name for p in raw.rglob("*") if p.is_file()) == sorted(
        p.name for p in full.rglob("*") if p.is_file()
    )
    for path in full.glob("*.exr"):
        a, b = read_exr(path), read_exr(raw / path.name)
        assert all(np.array_equal(a[c], b[c]) for c in a), path.name


def test_changed_config_renders_only_what_changed(rendered, ds, tmp_path):
    import shutil

    from src.render.volume_dataset import render_volumetric_dataset

    raw = tmp_path / "raw"
    shutil.copytree(rendered[0], raw)
    (raw / "mine-f0000-00004spp.exr").write_bytes(b"a user's file: no manifest entry")
    summary = render_volumetric_dataset({**ds, "reference_spp": 6}, raw, "auto", frames=[0])
    assert summary["files_rendered"] == 1 and summary["files_cached"] == 1  # the new reference only
    # The old references are gone, frame 1's too (outside this job's frames, but no frame has them now);
    # frame 1's noisy file stays for the job that renders frame 1, and the user's file stays.
    assert summary["files_removed"] == 2
    assert sorted(p.name for p in raw.glob("*.exr")) == [
        "fog_objects-0000-f0000-00002spp.exr",
        "fog_objects-0000-f0000-00006spp.exr",
        "fog_objects-0000-f0001-00002spp.exr",
        "mine-f0000-00004spp.exr",
    ]
    assert sorted(p.name for p in (raw / "manifest").iterdir()) == [
        "fog_objects-0000-f0000-00002spp.exr.json",
        "fog_objects-0000-f0000-00006spp.exr.json",
        "fog_objects-0000-f0001-00002spp.exr.json",
    ]


def test_bad_subsets_are_config_errors(ds):
    from src.render.render_dataset import scene_sources
    from src.render.volume_dataset import select_frames, select_scenes

    with pytest.raises(ConfigError) as err:
        select_scenes(scene_sources(ds), ["cloud-0007"])
    one_line_error(err, "dataset.render_scenes", "cloud-0007", "fog_objects-0000")
    with pytest.raises(ConfigError) as err:
        select_frames(ds, [0, 2])
    one_line_error(err, "dataset.render_frames", "[2]", "0-1")
    assert select_frames(ds, [1, 0, 1]) == [0, 1] and select_frames(ds, None) == [0, 1]


def test_frame_is_in_the_pass_seeds_and_the_surface_seeds_are_unchanged():
    from src.render.render_dataset import pass_seed

    assert pass_seed(0, "a", 4, "noisy", 0, frame=0) != pass_seed(0, "a", 4, "noisy", 0, frame=1)
    assert pass_seed(0, "a", 4, "noisy", 0, frame=0) != pass_seed(0, "a", 4, "noisy", 0)
    # the still-image datasets' seed of this key before frames existed
    key = [0, __import__("zlib").crc32(b"a"), 4, 1, 0]
    assert pass_seed(0, "a", 4, "noisy", 0) == int(np.random.SeedSequence(key).generate_state(1)[0])


# --- config and the command line ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("profile", "size", "frames", "noisy", "reference"),
    [
        ("smoke", (32, 24), 2, [4, 16], 64),
        ("cpu", (96, 64), 8, [4, 16], 256),
        ("paper", (1280, 720), 16, [16, 32, 64, 128], 4096),
    ],
)
def test_volumetric_sizes_per_profile(profile, size, frames, noisy, reference):
    cfg = compose_config(["dataset=volumetric", f"profile={profile}"])
    d = cfg.dataset
    assert ((d.width, d.height), d.frames, list(d.noisy_spp), d.reference_spp) == (
        size,
        frames,
        noisy,
        reference,
    )
    assert d.render_scenes is None and d.render_frames is None
    assert compose_config([f"profile={profile}"]).dataset.name == "procedural"  # still-image sizes untouched


@pytest.mark.slow
def test_render_stage_from_the_command_line(tmp_path):
    """~11 s: the smoke profile's 4 scenes x 2 frames (their preprocessing: tests/test_volume_shards.py)."""
    cmd, env = cli_job(
        ["stage=render", "dataset=volumetric", "profile=smoke", f"hydra.run.dir={tmp_path}/h"], tmp_path
    )
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    assert "render: 24 files (0 cached)" in result.stdout and "M samples/s" in result.stdout
    raw = tmp_path / "volumetric" / "smoke" / "raw"
    assert len(list(raw.glob("*-f000[01]-*spp.exr"))) == 24
    assert (tmp_path / "volumetric" / "smoke" / "render_summary.json").is_file()
