"""`dataset=noisebase` (issue 35): a Noisebase set converted into the volumetric sequences' raw layout
(values equal the reader's, stale files removed, an unchanged set not converted again), its config
checks, and (slow) the whole smoke pipeline of the sequence and per-frame models on a fixture set."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from omegaconf import OmegaConf

from src.data.ladder import read_ladder
from src.data.noisebase import convert_to_volume_exrs, read_frames, volume_frame_buffers
from src.data.splits import split_scenes
from src.data.volume_buffers import load_volume_exr
from src.errors import ConfigError, DataError
from src.render.ladder_render import noisebase_ladder
from src.schema.checks import check
from src.schema.dataset import NoisebaseDataset
from tests.conftest import compose_config, data_kind, one_line_cli_error, one_line_error
from tests.noisebase_fixture import write_test_sequence, write_training_sequence

ROOT = Path(__file__).resolve().parents[1]


def _training_set(root: Path, n=3, size=8, spp=4) -> None:
    for i in range(n):
        write_training_sequence(root / "train" / f"scene{i:04d}.zip", frames=2, size=size, spp=spp, seed=i)


def _ds(root: Path, **over) -> dict:
    ds = {
        "root": str(root),
        "format": "training",
        "files": "train/scene{index:04d}.zip",
        "sequences": [0, 1, 2],
        "frames": 2,
        "crop": None,
        "noisy_spp": [2, 4],
        "reference_spp": 64,
        "rendering_height": 64,
        "rendering_width": 96,
    }
    return ds | over


def test_conversion_writes_the_readers_buffers_and_keeps_only_what_the_config_makes(tmp_path):
    _training_set(tmp_path / "nb")
    raw = tmp_path / "raw"
    made = convert_to_volume_exrs(_ds(tmp_path / "nb"), raw)
    assert made["files_written"] == 3 * 2 * 3 and made["sequences"] == 3
    frames = read_frames(
        tmp_path / "nb" / "train" / "scene0001.zip", "training", [0, 1], 4, rendering=(64, 96)
    )
    want = volume_frame_buffers(frames[0], frames[1], 2)
    got, _ = load_volume_exr(raw / "scene0001-f0000-00002spp.exr")
    for name in ("color", "colorVariance", "albedo", "normal", "depth", "depthVariance", "motion"):
        np.testing.assert_array_equal(got[name], want[name], err_msg=name)
    assert np.abs(got["motion"]).max() > 0
    ref, _ = load_volume_exr(raw / "scene0001-f0001-00064spp.exr")
    np.testing.assert_array_equal(ref["color"], np.moveaxis(frames[1].reference, 0, -1))
    # unchanged: nothing written; fewer sequences and counts: the others' files go
    assert convert_to_volume_exrs(_ds(tmp_path / "nb"), raw)["files_written"] == 0
    convert_to_volume_exrs(_ds(tmp_path / "nb", sequences=[0, 2], noisy_spp=[4]), raw)
    assert sorted(p.name for p in raw.glob("scene0000-f0000-*.exr")) == [
        "scene0000-f0000-00004spp.exr",
        "scene0000-f0000-00064spp.exr",
    ]
    assert not list(raw.glob("scene0001-*"))
    # a conversion that fails part-way (scene0005.zip is missing) after rewriting the others in a 4x4
    # window leaves no record: the next one converts them again
    with pytest.raises(DataError):
        convert_to_volume_exrs(
            _ds(tmp_path / "nb", sequences=[0, 2, 5], noisy_spp=[4], crop=[0, 0, 4, 4]), raw
        )
    assert load_volume_exr(raw / "scene0000-f0000-00004spp.exr")[0]["color"].shape == (4, 4, 3)
    assert convert_to_volume_exrs(_ds(tmp_path / "nb", sequences=[0, 2], noisy_spp=[4]), raw)["files_written"]
    assert load_volume_exr(raw / "scene0000-f0000-00004spp.exr")[0]["color"].shape == (8, 8, 3)


def test_each_frame_flows_into_the_next_and_its_reference_file_carries_that_flow(tmp_path):
    for i in range(3):
        write_training_sequence(
            tmp_path / "nb" / "train" / f"scene{i:04d}.zip", frames=3, size=8, spp=4, seed=i
        )
    raw = tmp_path / "raw"
    convert_to_volume_exrs(_ds(tmp_path / "nb", frames=3, noisy_spp=[2]), raw)
    frames = read_frames(
        tmp_path / "nb" / "train" / "scene0002.zip", "training", [0, 1, 2], 4, rendering=(64, 96)
    )
    for f, following in ((0, frames[1]), (1, frames[2]), (2, None)):  # frame 1 into frame 2, not back to 0
        want = volume_frame_buffers(frames[f], following, 2)["motion"]
        for spp in (2, 64):  # the noisy file and the reference file
            got, _ = load_volume_exr(raw / f"scene0002-f{f:04d}-{spp:05d}spp.exr")
            np.testing.assert_array_equal(got["motion"], want, err_msg=f"{f} {spp}")
    assert np.abs(volume_frame_buffers(frames[1], frames[2], 2)["motion"]).max() > 0


def test_a_changed_store_or_window_converts_again_and_an_unchanged_one_is_cached(tmp_path):
    _training_set(tmp_path / "nb")
    raw, ds = tmp_path / "raw", _ds(tmp_path / "nb")
    assert convert_to_volume_exrs(ds, raw)["files_cached"] == 0
    cached = convert_to_volume_exrs(ds, raw)
    assert (cached["files_written"], cached["files_cached"], cached["seconds"]) == (0, 18, 0.0)
    # the same file names from another window of the stores
    assert convert_to_volume_exrs(ds | {"crop": [0, 0, 4, 4]}, raw)["files_written"] == 18
    assert convert_to_volume_exrs(ds | {"crop": [0, 0, 4, 4]}, raw)["files_written"] == 0
    # a store replaced by another of the same name (a new download): its size or time changed
    before = load_volume_exr(raw / "scene0001-f0000-00002spp.exr")[0]["color"]
    write_training_sequence(tmp_path / "nb" / "train" / "scene0001.zip", frames=2, size=8, spp=4, seed=42)
    assert convert_to_volume_exrs(ds | {"crop": [0, 0, 4, 4]}, raw)["files_written"] == 18
    assert not np.array_equal(load_volume_exr(raw / "scene0001-f0000-00002spp.exr")[0]["color"], before)


def test_a_test_format_set_is_one_store_per_frame(tmp_path):
    for k, name in enumerate(("bistro1", "kitchen", "bedroom")):
        write_test_sequence(tmp_path / "nb" / "test8", name, frames=2, height=12, width=10, spp=4, seed=k)
    ds = _ds(
        tmp_path / "nb",
        format="test",
        files="test8/{sequence_name}/frame{index:04d}.zip",
        sequences=["bistro1", "kitchen", "bedroom"],
        crop=[2, 1, 8, 8],
    )
    convert_to_volume_exrs(ds, tmp_path / "raw")
    got, _ = load_volume_exr(tmp_path / "raw" / "kitchen-f0001-00004spp.exr")
    (frame,) = read_frames(
        tmp_path / "nb" / "test8" / "kitchen" / "frame0001.zip", "test", [0], 4, [2, 1, 8, 8]
    )
    np.testing.assert_array_equal(got["color"], volume_frame_buffers(frame, None, 4)["color"])
    assert got["color"].shape == (8, 8, 3)


def test_the_ladder_averages_the_last_of_the_top_counts_samples_and_has_no_render_time(tmp_path):
    stores = [tmp_path / "nb" / "train" / f"scene{i:04d}.zip" for i in range(3)]
    written = [write_training_sequence(p, frames=2, size=8, spp=8, seed=i) for i, p in enumerate(stores)]
    radiance = written[1]["radiance"]  # (F, 3, H, W, S) in float64, from the fixture's own decoding

    def samples(lo, hi):  # the mean of stored samples lo..hi-1 per frame, (F, H, W, 3)
        return np.moveaxis(radiance[..., lo:hi].mean(-1), 1, -1)

    ladder = tmp_path / "ladder"
    made = noisebase_ladder(_ds(tmp_path / "nb", ladder_spp=[1, 2, 4]), ladder, ["scene0001", "scene9999"])
    assert (made["scenes"], made["files_rendered"]) == (["scene0001"], 2 * 3)
    got = read_ladder(ladder, "scene0001", [1, 2, 4], frames=2)
    for k in (1, 2, 4):  # the top count is 4: rung k holds stored samples 4-k..3
        np.testing.assert_allclose(got.frames[k], samples(4 - k, 4), rtol=1e-5, err_msg=str(k))
    assert all(math.isnan(s) for s in got.seconds.values())  # averaged, never rendered: no time
    assert not list(ladder.glob("scene0000*")) and not list(ladder.glob("scene0002*"))  # held out: 0001
    # unchanged: nothing averaged again; a new top count moves every rung to the new last samples and drops
    # the rungs the ladder no longer has
    assert (
        noisebase_ladder(_ds(tmp_path / "nb", ladder_spp=[1, 2, 4]), ladder, ["scene0001"])["files_cached"]
        == 6
    )
    again = noisebase_ladder(_ds(tmp_path / "nb", ladder_spp=[2, 8]), ladder, ["scene0001"])
    assert (again["files_rendered"], again["files_removed"]) == (4, 4)
    got = read_ladder(ladder, "scene0001", [2, 8], frames=2)
    np.testing.assert_allclose(got.frames[2], samples(6, 8), rtol=1e-5)
    np.testing.assert_allclose(got.frames[8], samples(0, 8), rtol=1e-5)
    with pytest.raises(DataError) as e:  # more than the stored samples
        noisebase_ladder(_ds(tmp_path / "nb", ladder_spp=[2, 16]), ladder, ["scene0001"])
    one_line_error(e, "scene0001.zip", "has 8 samples per pixel", "dataset.ladder_spp", "16")


def test_the_noisebase_ladder_holds_out_the_sequences_the_evaluation_scores():
    cfg = compose_config(["dataset=noisebase", "dataset.root=/data/nb", "dataset.sequences=[0,1,2,3,4,5]"])
    p = cfg.task.preprocess
    want = split_scenes([f"scene{i:04d}" for i in range(6)], p.split, p.split_seed)
    kind = data_kind(cfg)
    assert kind.ladder_scenes(cfg) == want["test"]
    cfg.task.eval.split = "val"
    assert kind.ladder_scenes(cfg) == want["val"] != want["test"]
    cfg.dataset.ladder_spp = []
    assert data_kind(cfg).ladder_scenes(cfg) == []


def _checked(*overrides):
    cfg = compose_config(["dataset=noisebase", "dataset.root=/data/nb", *overrides])
    return check(NoisebaseDataset, OmegaConf.to_container(cfg.dataset, resolve=True), "dataset.")


@pytest.mark.parametrize(
    ("overrides", "needles"),
    [
        (["dataset.root=???"], ["dataset.root", "missing"]),
        (["dataset.files=scenes/all.zip"], ["dataset.files='scenes/all.zip'", "{index}"]),
        (["dataset.format=test"], ["{sequence_name}"]),
        (["dataset.sequences=[a,b,c]"], ["dataset.sequences=['a', 'b', 'c']", "indices"]),
        (["dataset.crop=[0,0,0,8]"], ["dataset.crop=[0, 0, 0, 8]", "height, width >= 1"]),
        (["dataset.crop=[0,0,8]"], ["dataset.crop=[0, 0, 8]"]),
        (["dataset.noisy_spp=[1,4]"], ["noisy_spp"]),
        (["dataset.ladder_spp=[8]"], ["dataset.ladder_spp=[8]", "at least two"]),
        (["dataset.ladder_spp=[1,4096]"], ["dataset.ladder_spp", "[4096]", "below"]),
    ],
)
def test_a_bad_noisebase_config_is_one_line(overrides, needles):
    with pytest.raises(ConfigError) as e:
        _checked(*overrides)
    one_line_error(e, *needles)


def test_the_shipped_config_and_a_test_set_config_pass():
    assert _checked().format == "training"
    ok = _checked(
        "dataset.format=test",
        "dataset.files='t/{sequence_name}/frame{index:04d}.zip'",
        "dataset.sequences=[bistro1,kitchen,bedroom]",
    )
    assert ok.sequences == ["bistro1", "kitchen", "bedroom"]


def _run(tmp_path, *args):
    env = os.environ | {
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path}/mlflow.db",
        "NRBENCH_DATA_DIR": str(tmp_path / "data"),
        "OMP_NUM_THREADS": "1",
    }
    command = [
        sys.executable,
        "-m",
        "src.run",
        "dataset=noisebase",
        f"dataset.root={tmp_path}/nb",
        "profile=smoke",
        "dataset.files='train/scene{index:04d}.zip'",
        "dataset.rendering_height=64",
        "dataset.rendering_width=96",
        "dataset.crop=null",
        f"hydra.run.dir={tmp_path}/run",
        f"tracking.artifact_root={tmp_path}/art",
        f"report.name={tmp_path}/report",
        *args,
    ]
    return subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.slow
@pytest.mark.parametrize("model", ["unet_kpcn", "kpcn"])
def test_the_sequence_and_per_frame_models_train_and_evaluate_on_a_noisebase_set(tmp_path, model):
    _training_set(tmp_path / "nb", size=16, spp=8)  # the smoke ladder reaches 8 samples
    result = _run(
        tmp_path,
        f"model={model}",
        "stage=all",
        "dataset.volume_features=[color,color.var,albedo,albedo.var,normal,normal.var,depth,depth.var,motion]",
    )
    assert result.returncode == 0, (result.stdout + result.stderr)[-3000:]
    assert "render: 18 files from 3 Noisebase sequences" in result.stdout
    assert f"eval: {model} on 2 images" in result.stdout


@pytest.mark.slow
def test_a_missing_store_stops_the_job_with_one_line(tmp_path):
    _training_set(tmp_path / "nb", n=2, spp=8)  # scene0002.zip is missing
    one_line_cli_error(_run(tmp_path, "stage=render"), "scene0002.zip", "no such Noisebase ZipStore")
