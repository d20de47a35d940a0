"""The second, independent reference of the held-out volumetric sequences (`dataset.second_reference`,
issue 33): which files the render plans (`src/render/volume_dataset.py`, without Mitsuba), which scenes
it renders them for (`RenderedSequences.held_out_scenes`, the split preprocessing makes), how
preprocessing stores them (`src/data/volume_shards.py`: `reference2` in the whole held-out sequences
only) and passes them to the evaluation (`src/data/sequence_dataset.py`), the cache key, stale files;
the whole smoke pipeline with it to `eval_flicker_unbiased` (slow)."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from src.data.sequence_dataset import SequenceDataset
from src.data.splits import split_scenes
from src.data.volume_buffers import SECOND_REFERENCE_DIR, parse_volume_exr_name, volume_exr_name
from src.errors import DataError
from tests.conftest import ROOT, cli_job, compose_config, data_kind, one_line_error, smoke_config
from tests.test_volume_shards import FRACTIONS, FRAMES, SCENES, SPPS, _preprocess, _raw, synthetic_frame

REF = max(SPPS)
#: The held-out scenes of tests/test_volume_shards.py's synthetic data (its split: fractions, seed 0).
SPLIT = split_scenes(SCENES, FRACTIONS, 0)
HELD_OUT = SPLIT["val"] + SPLIT["test"]


def _second(scene: str) -> str:
    """The synthetic second reference of `scene`: another scene's frames (other values, same size)."""
    return f"{scene}~second"


def _loader(loaded: list[Path]):
    """A fake EXR reader: the synthetic frame its name says, the `_second` scene's for a file under
    reference2/; records every path it reads."""

    def load(path, buffers):
        path = Path(path)
        loaded.append(path)
        scene, frame, spp = parse_volume_exr_name(path)
        if path.parent.name == SECOND_REFERENCE_DIR:
            scene = _second(scene)
        return {k: synthetic_frame(scene, frame, spp)[k] for k in buffers}

    return load


def _with_second(raw: Path, scenes) -> Path:
    (raw / SECOND_REFERENCE_DIR).mkdir(exist_ok=True)
    for s in scenes:
        for f in range(FRAMES):
            (raw / SECOND_REFERENCE_DIR / volume_exr_name(s, f, REF)).touch()
    return raw


def _chw(frames) -> torch.Tensor:
    return torch.from_numpy(np.moveaxis(np.stack(frames).astype(np.float32), -1, -3))


@pytest.fixture(scope="module")
def with_second(tmp_path_factory):
    """Synthetic sequences whose held-out scenes have a second reference, prepared with the option on:
    (raw, prepared, summary, paths read)."""
    tmp = tmp_path_factory.mktemp("ref2")
    raw = _with_second(_raw(tmp / "raw"), HELD_OUT)
    loaded: list[Path] = []
    summary = _preprocess(raw, tmp / "out", load_fn=_loader(loaded), second_reference=True)
    return raw, tmp / "out", summary, loaded


def test_the_held_out_sequences_carry_the_second_reference_read_from_its_files(with_second):
    _, out, summary, loaded = with_second
    assert json.loads((out / "splits.json").read_text()) == SPLIT and summary["settings"]["second_reference"]
    for split in ("val", "test"):
        data = SequenceDataset(out, split, features=["color"])
        assert len(data) == 2 and "reference2" in data.batch_keys  # one sequence per noisy spp
        index = json.loads((out / "full" / split / "index.json").read_text())
        assert index["channels"]["reference2"] == ["r", "g", "b"]
        for item in data:
            scene = item["scene"]
            want = _chw([synthetic_frame(_second(scene), f, REF)["color"] for f in range(FRAMES)])
            assert torch.equal(item["reference2"], want)  # linear, every frame, in order
            assert not torch.equal(item["reference2"], item["reference"])
            assert torch.equal(
                item["reference"], _chw([synthetic_frame(scene, f, REF)["color"] for f in range(FRAMES)])
            )
    # read once per held-out scene and frame (not per noisy spp), never a train scene's
    second_reads = sorted(p.name for p in loaded if p.parent.name == SECOND_REFERENCE_DIR)
    assert second_reads == sorted(volume_exr_name(s, f, REF) for s in HELD_OUT for f in range(FRAMES))


def test_training_samples_and_train_sequences_hold_no_second_reference(with_second, tmp_path):
    raw, out, _, _ = with_second
    for split in ("train", "val"):
        index = json.loads((out / "patches" / split / "index.json").read_text())
        assert "reference2" not in index["channels"]
        for entry in index["shards"]:
            shard = torch.load(out / "patches" / split / entry["file"], weights_only=True)
            assert "reference2" not in shard and "reference" in shard
    # a train scene's second reference, were there one, is not read either (the render makes none)
    _with_second(raw, SPLIT["train"])
    loaded: list[Path] = []
    try:
        _preprocess(raw, tmp_path / "again", load_fn=_loader(loaded), second_reference=True)
    finally:
        for s in SPLIT["train"]:
            for f in range(FRAMES):
                (raw / SECOND_REFERENCE_DIR / volume_exr_name(s, f, REF)).unlink()
    assert {p.name.split("-f")[0] for p in loaded if p.parent.name == SECOND_REFERENCE_DIR} == set(HELD_OUT)


def test_without_the_option_nothing_is_stored_or_read(with_second, tmp_path):
    raw, _, _, _ = with_second
    loaded: list[Path] = []
    summary = _preprocess(raw, tmp_path / "out", load_fn=_loader(loaded))
    assert "second_reference" not in summary["settings"]
    assert not any(p.parent.name == SECOND_REFERENCE_DIR for p in loaded)
    data = SequenceDataset(tmp_path / "out", "test")
    assert "reference2" not in data.batch_keys and "reference2" not in data[0]
    index = json.loads((tmp_path / "out" / "full" / "test" / "index.json").read_text())
    assert "reference2" not in index["channels"]


def test_a_missing_second_reference_is_one_line(tmp_path):
    raw = _with_second(_raw(tmp_path / "raw"), HELD_OUT)
    gone = raw / SECOND_REFERENCE_DIR / volume_exr_name(SPLIT["test"][0], 2, REF)
    gone.unlink()
    with pytest.raises(DataError) as err:
        _preprocess(raw, tmp_path / "out", load_fn=_loader([]), second_reference=True)
    one_line_error(
        err,
        str(gone),
        repr(SPLIT["test"][0]),
        "dataset.second_reference",
        "1 of its 4 frames",
        "stage=render",
    )
    assert not (tmp_path / "out").exists()  # checked before any sequence is prepared


def test_the_stage_stores_the_second_reference_of_real_files_with_their_repairs(tmp_path):
    """`stage=preprocess` on written EXRs (the default loader): the held-out scenes' second references,
    one with a negative pixel the repair policy clamps (recorded under reference2/, apart from its
    reference's name), stored as read."""
    from src.data.volume_buffers import write_volume_exr
    from src.stages import preprocess

    cfg = smoke_config(
        tmp_path / "data",
        tmp_path / "run",
        ["dataset=volumetric", "dataset.second_reference=true", "task.preprocess.repair.negative=clamp"],
    )
    raw = Path(cfg.paths.raw)
    scenes = ("a-0000", "b-0000", "c-0000")
    for s in scenes:
        for f in range(2):
            for spp in (2, 16):
                write_volume_exr(raw / volume_exr_name(s, f, spp), synthetic_frame(s, f, spp))
    p = data_kind(cfg).preprocess_settings(cfg)
    split = split_scenes(scenes, p["split_fractions"], p["split_seed"])
    held_out = split["val"] + split["test"]
    second = {(s, f): synthetic_frame(_second(s), f, 16) for s in held_out for f in range(2)}
    second[held_out[0], 1]["color"][3, 4, 1] = -0.5
    for (s, f), frame in second.items():
        write_volume_exr(raw / SECOND_REFERENCE_DIR / volume_exr_name(s, f, 16), frame)
    summary = preprocess(cfg)
    assert summary["repairs"] == {f"reference2/{volume_exr_name(held_out[0], 1, 16)}": "negative: G=1"}
    second[held_out[0], 1]["color"][3, 4, 1] = 0.0
    prepared = Path(cfg.paths.prepared)
    for split_name in ("val", "test"):
        (item,) = [i for i in SequenceDataset(prepared, split_name) if i["spp"] == 2]
        assert torch.equal(item["reference2"], _chw([second[item["scene"], f]["color"] for f in range(2)]))


# --- the config: the scenes the render stage gives a second reference, the prepared data's cache key ---


def test_the_render_stage_picks_the_scenes_preprocessing_holds_out(tmp_path):
    """`held_out_scenes` of the smoke config is the val + test of a preprocessing of its scenes with the
    same config, and follows task.preprocess.split_seed; at the cpu profile, the twelve held-out scenes of
    the cpu data (val + test of their splits.json, six seeds per base, at issue 33)."""
    from src.render.render_dataset import scene_sources

    def held_out_scenes(config):
        return data_kind(config).held_out_scenes(config)

    cfg = smoke_config(tmp_path, tmp_path / "run", ["dataset=volumetric", "dataset.second_reference=true"])
    names = [s.name for s in scene_sources(OmegaConf.to_container(cfg.dataset, resolve=True))]
    raw = _raw(tmp_path / "raw", scenes=names, frames=2)
    settings = data_kind(cfg).preprocess_settings(cfg) | {"sequence_frames": 2}
    _with_second(raw, names)  # every scene has one, so the split alone decides
    summary = _preprocess(raw, tmp_path / "out", **settings, load_fn=_loader([]), progress=False)
    splits = json.loads((tmp_path / "out" / "full" / "test" / "index.json").read_text())
    assert summary["splits"] == {"train": 2, "val": 1, "test": 1}
    stored = {e["scene"] for split in ("val", "test") for e in json.loads(
        (tmp_path / "out" / "full" / split / "index.json").read_text())["shards"]}  # fmt: skip
    assert held_out_scenes(cfg) == sorted(stored) and len(stored) == 2 and splits["channels"]["reference2"]
    other = smoke_config(tmp_path, tmp_path / "run", ["dataset=volumetric", "task.preprocess.split_seed=3"])
    assert held_out_scenes(other) != held_out_scenes(cfg)
    cpu = compose_config(["dataset=volumetric", "profile=cpu"])
    assert cpu.dataset.second_reference is True
    assert held_out_scenes(cpu) == [
        "cloud-0002",
        "cloud-0003",
        "cloud-0004",
        "fog_objects-0000",
        "fog_objects-0002",
        "fog_objects-0004",
        "fog_objects-0005",
        "smoke_tabletop-0000",
        "smoke_tabletop-0002",
        "smoke_tabletop-0003",
        "smoke_tabletop-0004",
        "smoke_tabletop-0005",
    ]


def test_the_prepared_datas_key_changes_when_the_option_flips(tmp_path):
    raw = _raw(tmp_path / "raw")
    off = smoke_config(tmp_path, tmp_path / "run", ["dataset=volumetric"])
    on = smoke_config(tmp_path, tmp_path / "run", ["dataset=volumetric", "dataset.second_reference=true"])
    assert off.dataset.second_reference is False  # the smoke profile's
    kind_on, kind_off = data_kind(on), data_kind(off)
    assert kind_on.preprocess_key(on, raw) != kind_off.preprocess_key(off, raw)
    assert kind_on.preprocess_settings(on)["second_reference"] is True
    # folders made before the option keep their key
    assert "second_reference" not in kind_off.preprocess_settings(off)
    assert kind_off.preprocess_key(off, raw) == data_kind(off).preprocess_key(off, raw)


# --- the render plan and stale second references (no Mitsuba) ---


@pytest.fixture(scope="module")
def cpu_ds():
    return OmegaConf.to_container(compose_config(["dataset=volumetric", "profile=cpu"]).dataset, resolve=True)


def test_the_plan_renders_a_second_reference_with_other_seeds_for_the_held_out_scenes_only(cpu_ds):
    from src.render.volume_dataset import render_plan

    held_out = ["fog_objects-0000", "godrays-0000"]
    plain, plan = render_plan(cpu_ds), render_plan(cpu_ds, second_reference=held_out)
    second = [f for f in plan if f["role"] == "reference2"]
    assert [f for f in plan if f["role"] != "reference2"] == plain  # the other files unchanged
    assert len(plain) == 24 * 8 * 3 and len(second) == 2 * 8  # 4 bases x 6 seeds, 8 frames, 3 spp counts
    assert sorted((f["scene"], f["frame"]) for f in second) == [(s, f) for s in held_out for f in range(8)]
    by_file = {(f["scene"], f["frame"], f["role"]): f for f in plan}
    for f in second:
        first = by_file[f["scene"], f["frame"], "reference"]
        assert f["file"] == f"reference2/{first['file']}" and f["spp"] == first["spp"] == 256
        assert f["passes"] == first["passes"] and f["seeds"] != first["seeds"] and f["key"] != first["key"]
    seeds = [s for f in plan for s in f["seeds"]]
    assert len(set(seeds)) == len(seeds)  # no two passes of the dataset share random numbers
    assert len({f["key"] for f in plan}) == len(plan)
    # the seeds of the first reference and the noisy files are those the cpu data were rendered with
    first = by_file["cloud-0000", 0, "reference"]
    assert first["seeds"] == [1903622287] and first["key"] == "5ad38e5747971018"
    # a fanned-out job's subset: its scenes' second references only
    subset = render_plan(cpu_ds, scenes=["cloud-0000", "godrays-0000"], frames=[3], second_reference=held_out)
    assert [(f["scene"], f["role"]) for f in subset if f["role"] == "reference2"] == [
        ("godrays-0000", "reference2")
    ]


def _entry(folder: Path, name: str) -> None:
    (folder / "manifest").mkdir(parents=True, exist_ok=True)
    (folder / name).write_bytes(b"exr")
    (folder / "manifest" / f"{name}.json").write_text("{}")


def test_stale_second_references_are_removed_and_those_of_another_split_kept(tmp_path, cpu_ds):
    """With the option on, a second reference of a scene another split holds out (the other task's, or a
    split_seed before) stays; one of a frame, scene or reference count the dataset no longer has goes;
    with the option off every one goes; a user's file without an entry always stays."""
    from src.render.volume_dataset import remove_stale_volume_files

    ds = {**cpu_ds, "frames": 2}
    raw, second = tmp_path / "raw", tmp_path / "raw" / SECOND_REFERENCE_DIR
    for s in ("cloud-0000", "godrays-0000"):
        _entry(raw, volume_exr_name(s, 0, 256))
        _entry(second, volume_exr_name(s, 0, 256))
    stale = [volume_exr_name("godrays-0000", 2, 256), volume_exr_name("cloud-0009", 0, 256)]
    stale += [volume_exr_name("cloud-0000", 1, 64)]  # no frame 2, no 10th cloud, another reference count
    for name in stale:
        _entry(second, name)
    (second / "mine-f0000-00256spp.exr").write_bytes(b"a user's file: no entry")
    assert remove_stale_volume_files(ds, raw, True) == sorted(f"reference2/{n}" for n in stale)
    assert sorted(p.name for p in second.glob("*.exr")) == [
        "cloud-0000-f0000-00256spp.exr",
        "godrays-0000-f0000-00256spp.exr",
        "mine-f0000-00256spp.exr",
    ]
    assert sorted(p.name for p in (second / "manifest").iterdir()) == [
        "cloud-0000-f0000-00256spp.exr.json",
        "godrays-0000-f0000-00256spp.exr.json",
    ]
    assert sorted(p.name for p in raw.glob("*.exr")) == [
        volume_exr_name(s, 0, 256) for s in ("cloud-0000", "godrays-0000")
    ]
    assert remove_stale_volume_files(ds, raw, False) == [
        f"reference2/{volume_exr_name(s, 0, 256)}" for s in ("cloud-0000", "godrays-0000")
    ]  # the option off
    # outside .parked/ (set aside for a config that has the option on: src/render/stale_renders.py)
    kept = sorted(p.name for p in second.rglob("*") if p.is_file() and ".parked" not in p.parts)
    assert kept == ["mine-f0000-00256spp.exr"]
    assert sorted(p.name for p in (second / ".parked").glob("*.exr")) == sorted(
        [*stale, *(volume_exr_name(s, 0, 256) for s in ("cloud-0000", "godrays-0000"))]
    )
    assert len(list(raw.glob("*.exr"))) == 2  # the other files stay


# --- the pipeline ---


@pytest.mark.slow
def test_the_smoke_pipeline_with_a_second_reference_logs_the_floored_flicker(tmp_path):
    """The smoke profile's sequences rendered without, then preprocessed with `dataset.second_reference=true`
    (one line, exit 2: no second reference), rendered with it (only the held-out two scenes' second
    references, 2 frames each, are new), preprocessed, and a filter evaluated: its run logs
    eval_flicker_unbiased beside the other metrics."""
    import mlflow

    from tests.conftest import one_line_cli_error

    base = ["dataset=volumetric", "profile=smoke", f"hydra.run.dir={tmp_path}/h"]
    on = [*base, "dataset.second_reference=true"]

    def run(*args):
        cmd, env = cli_job(list(args), tmp_path)
        return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)

    for args, expect in (
        (["stage=render", *base], "render: 24 files (0 cached)"),
        (["stage=preprocess", *on], None),
        (["stage=render", *on], "render: 4 files (24 cached)"),
        (["stage=preprocess", *on], "preprocess: 8 noisy sequences"),
        (["stage=eval", "model=cross_bilateral", *on], "eval: cross_bilateral"),
    ):
        result = run(*args)
        if expect is None:
            one_line_cli_error(result, "reference2", "dataset.second_reference", "stage=render")
            continue
        assert result.returncode == 0, result.stderr[-3000:]
        assert expect in result.stdout, result.stdout[-2000:]
    raw = tmp_path / "volumetric" / "smoke" / "raw"
    assert len(list((raw / SECOND_REFERENCE_DIR).glob("*.exr"))) == 4
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path}/mlflow.db")
    runs = mlflow.search_runs(search_all_experiments=True, order_by=["start_time DESC"])
    metrics = runs.iloc[0]
    for key in ("eval_flicker_unbiased", "eval_noisy_flicker_unbiased", "eval_tpsnr", "eval_temporal"):
        assert np.isfinite(metrics[f"metrics.{key}"]), key
