"""Volumetric preprocessing (`src/data/volume_shards.py`, `sequence_dataset.py`, `volume_features.py`):
sequence samples and whole sequences from synthetic sequence EXRs, their channels, transforms, splits,
determinism, caching and errors; the stage from the command line (slow)."""

from __future__ import annotations

import json
import shutil
import subprocess

import numpy as np
import pytest
import torch

from src.data.sequence_dataset import SequenceDataset, SequencePatchDataset
from src.data.transforms import (
    inverse_log_modulus,
    inverse_volume_transform,
    log_modulus,
    log_modulus_variance,
)
from src.data.volume_buffers import VOLUME_EXR_BUFFERS, parse_volume_exr_name, volume_exr_name
from src.data.volume_features import (
    VOLUME_CANDIDATE_CHANNELS,
    VOLUME_FEATURE_BUFFERS,
    volume_feature_channels,
)
from src.data.volume_shards import SEQUENCE_CHANNELS, preprocess_volume_dataset, sequence_arrays
from src.errors import ConfigError, DataError
from tests.conftest import ROOT, cli_job, data_kind, one_line_error, smoke_config

SCENES = ("a-0000", "b-0000", "c-0000", "d-0000")
FRAMES, SPPS, H, W = 4, (2, 8, 64), 12, 16
FRACTIONS = {"train": 0.5, "val": 0.25, "test": 0.25}


def synthetic_frame(scene: str, frame: int, spp: int, h: int = H, w: int = W) -> dict[str, np.ndarray]:
    """Every buffer of one volumetric file, deterministic: random non-negative values, colour = surface +
    volume, and the pixel's (row, col, frame) in `albedo` and the frame in `scattered`, so that a sample's
    crop and frames can be read back from its inputs."""
    rng = np.random.default_rng([sum(map(ord, scene)), frame, spp])
    b = {n: 4 * rng.random((h, w, len(c)), dtype=np.float32) for n, c in VOLUME_EXR_BUFFERS.items()}
    b["color"] = b["surface"] + b["volume"]
    rows, cols = np.mgrid[:h, :w].astype(np.float32)
    b["albedo"] = np.stack([rows, cols, np.full_like(rows, frame)], axis=-1)
    b["scattered"] = np.full((h, w, 1), frame, np.float32)
    b["motion"] -= 2.0  # signed
    return b


def _load(path, buffers):
    frame = synthetic_frame(*parse_volume_exr_name(path))
    return {k: frame[k] for k in buffers}


def _raw(folder, scenes=SCENES, frames=FRAMES, spps=SPPS):
    folder.mkdir(parents=True, exist_ok=True)
    for s in scenes:
        for f in range(frames):
            for spp in spps:
                (folder / volume_exr_name(s, f, spp)).touch()
    return folder


def _preprocess(raw, out, **kw):
    args = dict(
        patch_size=4, patches_per_sequence=5, sequence_frames=3, split_fractions=FRACTIONS, split_seed=0,
        sample_seed=1, load_fn=_load, progress=False,
    )  # fmt: skip
    return preprocess_volume_dataset(raw, out, **(args | kw))


@pytest.fixture(scope="module")
def prepared(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("volprep")
    raw = _raw(tmp / "raw")
    return raw, tmp / "out", _preprocess(raw, tmp / "out")


def test_the_candidate_channels_are_named_per_buffer_without_world_points():
    assert len(VOLUME_CANDIDATE_CHANNELS) == 62 and len(set(VOLUME_CANDIDATE_CHANNELS)) == 62
    assert VOLUME_CANDIDATE_CHANNELS[:4] == ("color_r", "color_g", "color_b", "color_var")
    assert "position" not in VOLUME_FEATURE_BUFFERS and "scatter_position" not in VOLUME_FEATURE_BUFFERS
    assert not any(c.startswith(("position", "scatter_position")) for c in VOLUME_CANDIDATE_CHANNELS)
    assert VOLUME_CANDIDATE_CHANNELS[-2:] == ("motion_x", "motion_y")
    assert volume_feature_channels(["depth", "normal.var", "motion"]) == (
        "depth", "normal_var", "motion_x", "motion_y",
    )  # fmt: skip
    assert volume_feature_channels(None) == VOLUME_CANDIDATE_CHANNELS


@pytest.mark.parametrize(
    ("features", "needles"),
    [
        (["color", "colour"], ["dataset.volume_features[1]='colour'", "optionally with .var"]),
        (["motion.var"], ["dataset.volume_features[0]='motion.var'"]),
        (["color.grad"], ["dataset.volume_features[0]='color.grad'"]),
        (["position"], ["dataset.volume_features[0]='position'"]),
        (["depth", "depth"], ["dataset.volume_features: ['depth'] listed more than once"]),
        ([], ["dataset.volume_features=[]: expected a non-empty list"]),
    ],
)
def test_bad_volume_features_are_one_line(features, needles):
    with pytest.raises(ConfigError) as err:
        volume_feature_channels(features)
    one_line_error(err, *needles)


def test_shards_hold_named_sequence_samples_and_whole_sequences(prepared):
    raw, out, summary = prepared
    splits = json.loads((out / "splits.json").read_text())
    assert sorted(sum(splits.values(), [])) == list(SCENES)  # split by scene, each scene once
    assert summary["splits"] == {"train": 2, "val": 1, "test": 1}
    assert summary["noisy_sequences"] == 8 and summary["samples"] == {"train": 20, "val": 10}
    assert summary["full_sequences"] == {"val": 2, "test": 2}
    index = json.loads((out / "patches" / "train" / "index.json").read_text())
    assert index["channels"] == {k: list(v) for k, v in SEQUENCE_CHANNELS.items()}
    assert (index["patch_size"], index["sequence_frames"], index["volume_transform"]) == (4, 3, "log_modulus")
    assert {e["scene"] for e in index["shards"]} == set(splits["train"])
    shard = torch.load(out / "patches" / "train" / index["shards"][0]["file"], weights_only=True)
    assert shard["inputs"].shape == (5, 3, 62, 4, 4) and shard["inputs"].dtype == torch.float32
    for key in ("target", "target_surface", "target_volume", "color", "reference"):
        assert shard[key].shape == (5, 3, 3, 4, 4)
    assert shard["starts"].shape == (5,) and shard["corners"].shape == (5, 2)
    full = json.loads((out / "full" / "test" / "index.json").read_text())
    assert [e["spp"] for e in full["shards"]] == [2, 8] and full["shards"][0]["frames"] == FRAMES
    seq = torch.load(out / "full" / "test" / full["shards"][0]["file"], weights_only=True)
    assert seq["inputs"].shape == (FRAMES, 62, H, W) and seq["reference"].shape == (FRAMES, 3, H, W)
    assert not (out / "patches" / "test").exists() and not (out / "full" / "train").exists()
    assert json.loads((out / "whitening.json").read_text())["inputs"]["mean"].__len__() == 62


def test_a_sample_is_one_crop_over_consecutive_frames(prepared):
    _, out, _ = prepared
    ds = SequencePatchDataset(out, "train", features=["albedo", "scattered"], shuffle=False)
    items = list(ds)
    assert len(items) == len(ds) == 20
    for item in items:
        x = item["radiance_in"]  # (k, 4, P, P): albedo = (row, col, frame), scattered = frame
        r, c, s = int(item["corner"][0]), int(item["corner"][1]), int(item["start"])
        assert x.shape == (3, 4, 4, 4)
        frames = torch.arange(s, s + 3, dtype=torch.float32)
        assert torch.equal(x[:, 2, 0, 0], frames) and torch.equal(x[:, 3, 0, 0], frames)
        assert torch.equal(x[:, 0], (r + torch.arange(4.0))[None, :, None].expand(3, 4, 4))
        assert torch.equal(x[:, 1], (c + torch.arange(4.0))[None, None, :].expand(3, 4, 4))
        assert 0 <= s <= FRAMES - 3


def test_log_modulus_on_radiance_and_targets_invert_to_the_reference(prepared):
    _, out, _ = prepared
    seq = SequenceDataset(out, "test", features=["color", "color.var", "volume", "normal"])[0]
    scene, spp = seq["scene"], seq["spp"]
    noisy = [synthetic_frame(scene, f, spp) for f in range(FRAMES)]
    ref = [synthetic_frame(scene, f, 64) for f in range(FRAMES)]
    color = np.stack([n["color"] for n in noisy])
    chw = lambda a: torch.from_numpy(np.moveaxis(np.asarray(a, np.float32), -1, -3))  # noqa: E731
    x = seq["radiance_in"]
    torch.testing.assert_close(x[:, 0:3], chw(log_modulus(color)))
    var = np.stack([n["colorVariance"] for n in noisy])
    torch.testing.assert_close(x[:, 3:4], chw(log_modulus_variance(var, color)))
    torch.testing.assert_close(x[:, 4:7], chw(log_modulus(np.stack([n["volume"] for n in noisy]))))
    torch.testing.assert_close(x[:, 7:10], chw(np.stack([n["normal"] for n in noisy])))  # as is
    reference = chw(np.stack([r["color"] for r in ref]))
    assert torch.equal(seq["reference"], reference) and torch.equal(seq["color"], chw(color))
    torch.testing.assert_close(inverse_volume_transform(seq["radiance_target"], "log_modulus"), reference)
    torch.testing.assert_close(inverse_log_modulus(seq["radiance_t"]), chw(color))
    torch.testing.assert_close(seq["motion"], chw(np.stack([n["motion"] for n in noisy])))
    assert seq["motion"].min() < 0  # signed, untransformed
    # The frame-batch guides and parts come whatever the selection (here: no albedo, no surface).
    torch.testing.assert_close(seq["albedo"], chw(np.stack([n["albedo"] for n in noisy])))
    torch.testing.assert_close(
        inverse_log_modulus(seq["surface_t"]), chw(np.stack([n["surface"] for n in noisy]))
    )
    assert seq["depth"].shape[1] == 1 and seq["normal"].shape[1] == 3
    surface = chw(np.stack([r["surface"] for r in ref]))
    torch.testing.assert_close(inverse_volume_transform(seq["target_surface"], "log_modulus"), surface)


def test_distances_share_one_scale_per_sequence_and_none_is_linear():
    noisy = [synthetic_frame("a-0000", f, 2) for f in range(3)]
    ref = [synthetic_frame("a-0000", f, 64) for f in range(3)]
    arrays = sequence_arrays(noisy, ref, "none")
    ch = {name: i for i, name in enumerate(VOLUME_CANDIDATE_CHANNELS)}
    depth = np.stack([n["depth"][..., 0] for n in noisy])
    scatter = np.stack([n["scatter_depth"][..., 0] for n in noisy])
    media = np.stack([n["scatter_media_distance"][..., 0] for n in noisy])
    scale = max(depth.max(), scatter.max(), media.max())
    np.testing.assert_allclose(arrays["inputs"][..., ch["depth"]], depth / scale, rtol=1e-6)
    np.testing.assert_allclose(arrays["inputs"][..., ch["scatter_depth"]], scatter / scale, rtol=1e-6)
    assert np.array_equal(arrays["inputs"][..., ch["color_r"]], np.stack([n["color"][..., 0] for n in noisy]))
    assert np.array_equal(arrays["target"], np.stack([r["color"] for r in ref]))
    ot = np.stack([n["optical_thickness"] for n in noisy])
    np.testing.assert_allclose(sequence_arrays(noisy, ref, "log_modulus")["inputs"][..., 36:39], np.log1p(ot))


def test_features_are_selected_by_name_and_whitened(prepared):
    _, out, _ = prepared
    all_ch = next(iter(SequencePatchDataset(out, "val", shuffle=False)))
    some = next(iter(SequencePatchDataset(out, "val", shuffle=False, features=["depth", "color.var"])))
    assert all_ch["radiance_in"].shape[1] == 62 and some["radiance_in"].shape[1] == 2
    i = {n: k for k, n in enumerate(VOLUME_CANDIDATE_CHANNELS)}
    assert torch.equal(some["radiance_in"][:, 0], all_ch["radiance_in"][:, i["depth"]])
    assert torch.equal(some["radiance_in"][:, 1], all_ch["radiance_in"][:, i["color_var"]])
    white = next(iter(SequencePatchDataset(out, "val", shuffle=False, whitening=out / "whitening.json")))
    stats = json.loads((out / "whitening.json").read_text())["inputs"]
    mean, std = (torch.tensor(stats[k], dtype=torch.float32)[:, None, None] for k in ("mean", "std"))
    torch.testing.assert_close(white["radiance_in"], (all_ch["radiance_in"] - mean) / std)
    assert torch.equal(white["radiance_t"], all_ch["radiance_t"])
    some_white = SequencePatchDataset(
        out, "val", shuffle=False, features=["depth", "color.var"], whitening=out / "whitening.json"
    )
    torch.testing.assert_close(
        next(iter(some_white))["radiance_in"], white["radiance_in"][:, [i["depth"], i["color_var"]]]
    )
    with pytest.raises(ConfigError) as err:
        SequenceDataset(out, "test", features=["colour"])
    one_line_error(err, "dataset.volume_features[0]='colour'")


def test_the_same_seeds_give_the_same_files_and_a_new_seed_other_samples(prepared, tmp_path):
    raw, out, _ = prepared
    _preprocess(raw, tmp_path / "again")
    for path in (out / "patches").rglob("*.pt"):
        a = torch.load(path, weights_only=True)
        b = torch.load(tmp_path / "again" / path.relative_to(out), weights_only=True)
        assert all(torch.equal(a[k], b[k]) for k in a), path
    _preprocess(raw, tmp_path / "other", sample_seed=2)
    name = next((out / "patches" / "train").glob("*.pt")).relative_to(out)
    a, b = (torch.load(d / name, weights_only=True) for d in (out, tmp_path / "other"))
    assert not torch.equal(a["corners"], b["corners"]) or not torch.equal(a["starts"], b["starts"])


def test_bad_settings_and_data_are_one_line(tmp_path):
    raw = _raw(tmp_path / "raw", frames=2)
    with pytest.raises(ConfigError) as err:
        _preprocess(raw, tmp_path / "out")
    one_line_error(err, "dataset.preprocess.sequence_frames=3", "2 frame(s) of scene 'a-0000'")
    with pytest.raises(ConfigError) as err:
        _preprocess(raw, tmp_path / "out", sequence_frames=2, volume_transform="log")
    one_line_error(err, "dataset.preprocess.volume_transform='log'", "'log_modulus'")
    with pytest.raises(ConfigError) as err:
        _preprocess(raw, tmp_path / "out", sequence_frames=2, patch_size=20)
    one_line_error(err, "task.preprocess.patch_size=20", "12x16")
    (raw / volume_exr_name("a-0000", 1, 64)).unlink()
    with pytest.raises(DataError) as err:
        _preprocess(raw, tmp_path / "out", sequence_frames=2)
    one_line_error(err, "'a-0000' frame 1 lacks the [64] spp")


def test_real_exr_files_load_with_the_default_loader(tmp_path):
    """`write_volume_exr` files, three 8x6 scenes of 2 frames: the default loader reads only the buffers
    it needs, and the stored colour is the file's."""
    from src.data.volume_buffers import write_volume_exr

    raw = tmp_path / "raw"
    for s in ("a-0000", "b-0000", "c-0000"):
        for f in range(2):
            for spp in (2, 16):
                write_volume_exr(raw / volume_exr_name(s, f, spp), synthetic_frame(s, f, spp, 6, 8))
    summary = _preprocess(raw, tmp_path / "out", sequence_frames=2, load_fn=None, split_fractions=FRACTIONS)
    assert summary["samples"]["train"] == 5
    seq = SequenceDataset(tmp_path / "out", "test")[0]
    want = np.stack([synthetic_frame(seq["scene"], f, 2, 6, 8)["color"] for f in range(2)])
    assert torch.equal(seq["color"], torch.from_numpy(np.moveaxis(want, -1, -3)))


@pytest.mark.slow
def test_render_and_preprocess_from_the_command_line(tmp_path):
    """~25 s: the smoke profile's sequences rendered, preprocessed, and a rerun that does nothing."""
    args = ["dataset=volumetric", "profile=smoke", f"hydra.run.dir={tmp_path}/h"]
    for stage, expect in (
        ("render", "render: 24 files"),
        ("preprocess", "preprocess: 8 noisy sequences"),
        ("preprocess", "preprocess: up to date"),
    ):
        cmd, env = cli_job([f"stage={stage}", *args], tmp_path)
        result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
        assert result.returncode == 0, result.stderr[-3000:]
        assert expect in result.stdout, result.stdout[-2000:]
    prepared = tmp_path / "volumetric" / "smoke" / "prepared"
    item = next(iter(SequencePatchDataset(prepared, "train")))
    assert item["radiance_in"].shape == (2, 62, 8, 8)
    assert len(SequenceDataset(prepared, "test")) == 2


# --- the stage: wiring, cache, job-start checks ---------------------------------------------------------


def _stage_config(tmp_path, *overrides, dataset="volumetric"):
    return smoke_config(tmp_path / "data", tmp_path / "run", [f"dataset={dataset}", *overrides])


def _write_raw(cfg):
    from pathlib import Path

    from src.data.volume_buffers import write_volume_exr

    raw = Path(cfg.paths.raw)
    for s in ("a-0000", "b-0000", "c-0000"):
        for f in range(cfg.dataset.frames):
            for spp in (2, 16):
                write_volume_exr(raw / volume_exr_name(s, f, spp), synthetic_frame(s, f, spp))


def test_the_stage_preprocesses_once_and_again_when_a_volumetric_setting_changes(tmp_path, capsys):
    from src.stages import preprocess

    cfg = _stage_config(tmp_path)
    _write_raw(cfg)
    summary = preprocess(cfg)
    assert summary["samples"] == {"train": 6, "val": 6} and summary["settings"]["sequence_frames"] == 2
    assert "preprocess: 3 noisy sequences: 6 train / 6 val samples of 2 frames" in capsys.readouterr().out
    prepared = tmp_path / "data" / "volumetric" / "smoke" / "prepared"
    assert (prepared / "preprocess_provenance.json").is_file()
    assert next(iter(SequencePatchDataset(prepared, "train")))["radiance_in"].shape == (2, 62, 8, 8)
    preprocess(_stage_config(tmp_path, "task.eval.tile=8"))  # no preprocessing setting
    assert "up to date" in capsys.readouterr().out
    summary = preprocess(_stage_config(tmp_path, "dataset.preprocess.sequence_frames=1"))
    assert "up to date" not in capsys.readouterr().out and summary["settings"]["sequence_frames"] == 1


def test_prepared_data_of_another_configuration_are_refused_at_job_start(tmp_path):
    """A stage that reads `paths.prepared` without preprocessing first stops with one line when the folder
    was made with other preprocessing settings or from other raw data (src/data/prepared_check.py)."""
    from src.data.volume_buffers import write_volume_exr
    from src.stages import preprocess, task_of

    mine = f"paths.raw={tmp_path}/my_sequences"  # a user's own raw folder, named at preprocess time only
    made = _stage_config(tmp_path, mine)
    _write_raw(made)
    preprocess(made)
    cfg = _stage_config(tmp_path)
    for stage in ("train", "eval", "select_features"):
        task_of(cfg).check_stages([stage], cfg)  # same settings, the raw data it was made from
    evaluation_only = _stage_config(tmp_path, "task.eval.tile=8")  # no preprocessing setting
    task_of(evaluation_only).check_stages(["train"], evaluation_only)
    other = _stage_config(tmp_path, "dataset.preprocess.sequence_frames=1")
    with pytest.raises(ConfigError) as excinfo:
        task_of(other).check_stages(["train"], other)
    one_line_error(
        excinfo, f"{made.paths.prepared}:", "dataset.preprocess", "my_sequences", "run stage=preprocess"
    )
    task_of(other).check_stages(["preprocess", "train"], other)  # the job makes them again first
    task_of(other).check_stages(["render"], other)  # reads no prepared data
    # the whole data folder moved (the record's raw path points nowhere): this config's paths.raw decides
    moved = tmp_path / "moved"
    shutil.copytree(tmp_path / "my_sequences", moved / "raw")
    shutil.copytree(str(made.paths.prepared), moved / "prepared")
    here = _stage_config(tmp_path, f"paths.raw={moved}/raw", f"paths.prepared={moved}/prepared")
    shutil.rmtree(tmp_path / "my_sequences")
    task_of(here).check_stages(["train"], here)
    elsewhere = _stage_config(tmp_path, f"paths.raw={tmp_path}/none", f"paths.prepared={moved}/prepared")
    with pytest.raises(ConfigError):  # neither the recorded nor this config's raw data made it
        task_of(elsewhere).check_stages(["train"], elsewhere)
    shutil.copytree(moved / "raw", tmp_path / "my_sequences")
    # the raw data changed since (one more sequence)
    write_volume_exr(tmp_path / "my_sequences" / "d-0000-f0000-00002spp.exr", synthetic_frame("d-0000", 0, 2))
    with pytest.raises(ConfigError):
        task_of(cfg).check_stages(["eval"], cfg)


@pytest.mark.parametrize("stage", ["train", "eval", "all"])
def test_every_stage_of_the_volumetric_dataset_passes_the_job_start_checks(stage, tmp_path):
    """Issue 17 lifted the refusal of train and eval: the sequence trainer and evaluation run them."""
    from src.stages import stages_to_run, task_of

    cfg = _stage_config(tmp_path, f"stage={stage}", "model=unet_kpcn")
    task_of(cfg).check_stages(stages_to_run(cfg), cfg)


def test_a_window_longer_than_the_sequences_is_refused_at_job_start(tmp_path):
    from src.stages import task_of

    cfg = _stage_config(tmp_path, "dataset.preprocess.sequence_frames=3")
    with pytest.raises(ConfigError) as err:
        task_of(cfg).check_stages(["preprocess"], cfg)
    one_line_error(err, "dataset.preprocess.sequence_frames=3", "dataset.frames=2")


def test_the_volume_channel_resolver_counts_the_selected_channels():
    from omegaconf import OmegaConf

    cfg = OmegaConf.create({"f": ["color", "depth.var", "motion"], "n": "${nrbench.volume_channels:${f}}"})
    assert cfg.n == 6
    assert OmegaConf.create({"f": None, "n": "${nrbench.volume_channels:${f}}"}).n == 62


@pytest.mark.parametrize(
    "dataset,profile,key",
    [
        ("procedural", "smoke", "70d9a00aba7f65a5"),
        ("procedural", "cpu", "b9cf4fe505996156"),
        ("volumetric", "smoke", "1b28f01a07c2a346"),
        ("volumetric", "cpu", "2c310287714f99b4"),
    ],
)
def test_the_prepared_datas_cache_key_survived_the_move_of_the_sequences_options(
    tmp_path, dataset, profile, key
):
    """The keys as the code computed them before the sequences' options moved from `task:` to `dataset:`
    (issue 44, at 876253f), on a fixed raw folder (its fingerprint is names and sizes): folders prepared
    before the move are still current, for either kind, and a still image's key never held the
    sequences' settings."""
    raw = tmp_path / "raw"
    raw.mkdir()
    (raw / "a-00004spp.exr").write_bytes(b"x" * 10)
    (raw / "b-00016spp.exr").write_bytes(b"y" * 7)
    cfg = smoke_config(tmp_path / "data", tmp_path / "run", [f"dataset={dataset}", f"profile={profile}"])
    assert data_kind(cfg).preprocess_key(cfg, raw) == key
