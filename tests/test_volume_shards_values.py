"""`src/data/volume_shards.py` by value, fast (the `volume_shards` mutation group's tests): the buffers'
transforms, the stored sequences and samples recomputed here from the synthetic frames, the sample
positions, the indices and the summary, and the whitening statistics recomputed from the train shards.
Tiny sequences (four scenes of three 8 x 8 frames at 2, 8 and 64 spp), well under a second."""

from __future__ import annotations

import json
import time
import zlib

import numpy as np
import pytest
import torch

from src.data.transforms import inverse_volume_transform, volume_transform
from src.data.volume_buffers import parse_volume_exr_name
from src.data.volume_features import VALUE_KINDS, VOLUME_FEATURE_BUFFERS
from src.data.volume_shards import (
    SEQUENCE_CHANNELS,
    preprocess_volume_dataset,
    sequence_arrays,
    transform_pair,
)
from src.errors import ConfigError, DataError
from tests.conftest import one_line_error
from tests.test_volume_shards import _raw, synthetic_frame

FRAMES, SPPS, H, W, P, K, N = 3, (2, 8, 64), 8, 8, 4, 2, 3
FRACTIONS = {"train": 0.5, "val": 0.25, "test": 0.25}
DISTANCES = ("depth", "scatter_depth", "scatter_media_distance")


def _load(path, buffers):
    frame = synthetic_frame(*parse_volume_exr_name(path), h=H, w=W)
    return {k: frame[k] for k in buffers}


def _preprocess(raw, out, **kw):
    args = dict(
        patch_size=P, patches_per_sequence=N, sequence_frames=K, split_fractions=FRACTIONS, split_seed=0,
        sample_seed=1, load_fn=_load, progress=False,
    )  # fmt: skip
    return preprocess_volume_dataset(raw, out, **(args | kw))


@pytest.fixture
def prepared(tmp_path):
    """Function-scoped (~0.2 s): under mutmut, a module fixture's calls count as hits of the first test
    only, and a mutant would run only that test."""
    tmp = tmp_path
    raw = _raw(tmp / "raw", frames=FRAMES, spps=SPPS)
    start = time.perf_counter()
    summary = _preprocess(raw, tmp / "out")
    return raw, tmp / "out", summary | {"elapsed": time.perf_counter() - start}


def _lm(x):
    return np.sign(x) * np.log1p(np.abs(x))


def expected_arrays(scene, spp, transform="log_modulus"):
    """The stored (F, H, W, C) arrays of one noisy sequence, from the module docstring and
    `volume_features`' kinds: radiance/unbounded under the transform with variance / (1 + mean|x|)^2,
    distances over the sequence's largest distance (variance over its square), the rest as is."""
    noisy = [synthetic_frame(scene, f, spp, H, W) for f in range(FRAMES)]
    ref = [synthetic_frame(scene, f, 64, H, W) for f in range(FRAMES)]
    b = {k: np.stack([n[k] for n in noisy]).astype(np.float64) for k in noisy[0]}
    scale = max(b[d].max() for d in DISTANCES)
    parts = []
    for buffer in VOLUME_FEATURE_BUFFERS:
        value, var = b[buffer], b.get(f"{buffer}Variance") if buffer != "motion" else None
        kind = VALUE_KINDS[buffer]
        if kind in ("radiance", "unbounded") and transform == "log_modulus":
            value, var = _lm(value), var / (1 + np.abs(value).mean(-1, keepdims=True)) ** 2
        elif kind == "distance":
            value, var = value / scale, var / scale**2
        parts += [value] if var is None else [value, var]
    lin = lambda key: np.stack([r[key] for r in ref]).astype(np.float64)  # noqa: E731
    t = _lm if transform == "log_modulus" else (lambda x: x)
    return {
        "inputs": np.concatenate(parts, axis=-1),
        "target": t(lin("color")),
        "target_surface": t(lin("surface")),
        "target_volume": t(lin("volume")),
        "color": b["color"],
        "reference": lin("color"),
    }


def _index(out, kind, split):
    return json.loads((out / kind / split / "index.json").read_text())


# --- the transforms ---------------------------------------------------------------------------------------


def test_volume_transform_is_the_signed_log_modulus_or_the_identity():
    x = np.array([-50.0, -0.5, 0.0, 0.25, 3.0])
    np.testing.assert_allclose(volume_transform(x, "log_modulus"), _lm(x), rtol=1e-14)
    np.testing.assert_allclose(inverse_volume_transform(_lm(x), "log_modulus"), x, rtol=1e-12)
    t = torch.from_numpy(x)
    torch.testing.assert_close(volume_transform(t, "log_modulus"), torch.from_numpy(_lm(x)))
    torch.testing.assert_close(inverse_volume_transform(torch.from_numpy(_lm(x)), "log_modulus"), t)
    assert volume_transform(x, "none") is x and inverse_volume_transform(t, "none") is t
    for f in (volume_transform, inverse_volume_transform):
        with pytest.raises(ConfigError) as err:
            f(x, "log")
        one_line_error(err, "dataset.preprocess.volume_transform='log'", "'log_modulus'", "'none'")


def test_transform_pair_by_kind_with_negative_values_and_a_zero_distance_scale():
    rng = np.random.default_rng(0)
    value = rng.normal(0, 3, (2, 3, 3))  # signed, unequal channels
    var = rng.random((2, 3, 1))
    lm_var = var / (1 + np.abs(value).mean(-1, keepdims=True)) ** 2
    for kind in ("radiance", "unbounded"):
        v, s = transform_pair(kind, value, var, "log_modulus", 7.0)
        np.testing.assert_allclose(v, _lm(value), rtol=1e-14)
        np.testing.assert_allclose(s, lm_var, rtol=1e-14)
        v, s = transform_pair(kind, value, None, "log_modulus", 7.0)
        assert s is None and np.allclose(v, _lm(value))
        v, s = transform_pair(kind, value, var, "none", 7.0)
        assert v is value and s is var
    v, s = transform_pair("distance", value, var, "log_modulus", 4.0)
    np.testing.assert_allclose(v, value / 4.0, rtol=1e-15)
    np.testing.assert_allclose(s, var / 16.0, rtol=1e-15)
    assert transform_pair("distance", value, None, "none", 4.0)[1] is None
    v, s = transform_pair("distance", value, var, "none", 0.5)  # a scale below 1 still divides
    np.testing.assert_allclose(v, 2 * value, rtol=1e-15)
    np.testing.assert_allclose(s, 4 * var, rtol=1e-15)
    v, s = transform_pair("distance", value, var, "none", 0.0)  # nothing hit: zeros, no division
    assert np.array_equal(v, np.zeros_like(value)) and np.array_equal(s, np.zeros_like(var))
    assert transform_pair("distance", value, None, "none", 0.0)[1] is None
    v, s = transform_pair("as_is", value, var, "log_modulus", 4.0)
    assert v is value and s is var
    with pytest.raises(ValueError, match="unknown value kind 'angle'"):
        transform_pair("angle", value, var, "log_modulus", 4.0)


def test_sequence_arrays_by_value_under_both_transforms():
    noisy = [synthetic_frame("b-0000", f, 8, H, W) for f in range(FRAMES)]
    ref = [synthetic_frame("b-0000", f, 64, H, W) for f in range(FRAMES)]
    for transform in ("log_modulus", "none"):
        got = sequence_arrays(noisy, ref, transform)
        want = expected_arrays("b-0000", 8, transform)
        assert set(got) == set(want)
        for key, value in want.items():
            assert got[key].dtype == np.float32 and got[key].shape == value.shape, key
            np.testing.assert_allclose(got[key], value, rtol=2e-6, atol=1e-6, err_msg=key)


def test_half_precision_frames_are_stored_as_float32_computed_in_float32():
    """A loader's float16 buffers are cast to float32 before any transform: in half precision
    log1p and the variance quotient would be off by ~1e-3."""
    noisy = [
        {k: v.astype(np.float16) for k, v in synthetic_frame("c-0000", f, 2, H, W).items()} for f in range(2)
    ]
    ref = [
        {k: v.astype(np.float16) for k, v in synthetic_frame("c-0000", f, 64, H, W).items()} for f in range(2)
    ]
    got = sequence_arrays(noisy, ref, "log_modulus")
    assert all(v.dtype == np.float32 for v in got.values())
    color = np.stack([n["color"] for n in noisy]).astype(np.float64)
    var = np.stack([n["colorVariance"] for n in noisy]).astype(np.float64)
    np.testing.assert_allclose(got["inputs"][..., :3], _lm(color), rtol=2e-6)
    np.testing.assert_allclose(
        got["inputs"][..., 3:4], var / (1 + color.mean(-1, keepdims=True)) ** 2, rtol=2e-6
    )
    np.testing.assert_allclose(
        got["target"], _lm(np.stack([r["color"] for r in ref]).astype(np.float64)), rtol=2e-6
    )


def test_malformed_sequences_are_one_line_data_errors():
    noisy = [synthetic_frame("a-0000", f, 2, H, W) for f in range(2)]
    ref = [synthetic_frame("a-0000", f, 64, H, W) for f in range(2)]
    without = lambda frame, key: {k: v for k, v in frame.items() if k != key}  # noqa: E731
    small = [synthetic_frame("a-0000", f, 64, 4, W) for f in range(2)]
    cases = [
        (noisy, ref[:1], ["seq x: 2 noisy frames, 1 reference frames"]),
        ([noisy[0], without(noisy[1], "depth")], ref, ["seq x", "'depth' is missing"]),
        ([noisy[0], {**noisy[1], "albedo": noisy[1]["albedo"][:4]}], ref, ["seq x", "'albedo' differs"]),
        (noisy, small, ["seq x: frames of (8, 8), reference (4, 8)"]),
        (noisy, [without(r, "volume") for r in ref], ["seq x reference: buffer 'volume' is missing"]),
    ]
    for n, r, needles in cases:
        with pytest.raises(DataError) as err:
            sequence_arrays(n, r, "log_modulus", "seq x")
        one_line_error(err, *needles)
    with pytest.raises(DataError) as err:
        sequence_arrays(noisy, ref[:1], "none")
    one_line_error(err, "sequence: 2 noisy frames, 1 reference frames")  # the default `what`
    with pytest.raises(ConfigError) as err:
        sequence_arrays(noisy, ref, "log")
    one_line_error(err, "dataset.preprocess.volume_transform='log'")


def test_a_frames_importance_is_the_thesis_map_or_the_monte_carlo_variance_map():
    from src.data.patch_sampling import configured_importance_map, importance_map, thesis_importance_map

    frame = synthetic_frame("a-0000", 0, 2, H, W)
    thesis = {"importance": "thesis", "importance_window": 1.5, "patch_size": 4}
    np.testing.assert_array_equal(  # 1.5 patches of 4 = 6 pixels -> the odd 7
        configured_importance_map(frame, thesis), thesis_importance_map(frame["color"], frame["normal"], 7)
    )
    mc = {"importance": "mc_variance", "importance_percentile": 80.0}
    want = importance_map(frame["colorVariance"], frame["normalVariance"], percentile=80.0)
    np.testing.assert_array_equal(configured_importance_map(frame, mc), want)
    assert not np.array_equal(want, importance_map(frame["colorVariance"], frame["normalVariance"]))
    assert not np.allclose(want, configured_importance_map(frame, thesis))


# --- the prepared folder ----------------------------------------------------------------------------------


def test_the_indices_and_the_summary_name_every_shard_by_value(prepared):
    raw, out, summary = prepared
    splits = json.loads((out / "splits.json").read_text())
    assert sorted(sum(splits.values(), [])) == ["a-0000", "b-0000", "c-0000", "d-0000"]
    channels = {key: list(names) for key, names in SEQUENCE_CHANNELS.items()}
    for kind, split in (("patches", "train"), ("patches", "val"), ("full", "val"), ("full", "test")):
        index = _index(out, kind, split)
        entries = [
            {
                "file": f"{scene}-{spp:05d}spp.pt", "scene": scene, "spp": spp, "reference_spp": 64,
                "frames": FRAMES, **({"n_samples": N} if kind == "patches" else {"height": H, "width": W}),
            }
            for scene in splits[split]
            for spp in SPPS[:-1]
        ]  # fmt: skip
        want = {
            "kind": kind, "split": split, "dtype": "float32",
            "layout": "(n, k, C, P, P)" if kind == "patches" else "(F, C, H, W)",
            "volume_transform": "log_modulus", "channels": channels, "shards": entries,
            **({"patch_size": P, "sequence_frames": K} if kind == "patches" else {}),
        }  # fmt: skip
        assert index == want, (kind, split)
    assert not (out / "patches" / "test").exists() and not (out / "full" / "train").exists()
    settings = {
        "patch_size": P, "patches_per_sequence": N, "sequence_frames": K, "split_fractions": FRACTIONS,
        "split_seed": 0, "sample_seed": 1, "volume_transform": "log_modulus", "candidates_factor": 4.0,
        "min_keep_prob": 0.1, "min_distance": None, "importance": "thesis", "importance_window": 1.0,
        "importance_percentile": 99.0, "whiten_eps": 1e-6,
    }  # fmt: skip
    summary = dict(summary)
    assert 0 < summary.pop("seconds") <= summary.pop("elapsed") + 1e-3  # the run's duration, rounded
    assert summary == {
        "raw_dir": str(raw), "splits": {"train": 2, "val": 1, "test": 1}, "noisy_sequences": 8,
        "samples": {"train": 4 * N, "val": 2 * N}, "full_sequences": {"val": 2, "test": 2},
        "input_channels": 62, "settings": settings,
    }  # fmt: skip
    written = json.loads((out / "summary.json").read_text())
    assert written.pop("seconds") > 0 and written == summary


def test_exr_files_are_read_by_the_default_loader(tmp_path):
    """Real `write_volume_exr` files (4 x 4, two frames, three scenes) and no `load_fn`: the stored noisy and
    reference colours are the files'."""
    from src.data.volume_buffers import volume_exr_name, write_volume_exr

    frames = {}
    for s in ("a-0000", "b-0000", "c-0000"):
        for f in range(2):
            for spp in (2, 16):
                frames[s, f, spp] = synthetic_frame(s, f, spp, 4, 4)
                write_volume_exr(tmp_path / "raw" / volume_exr_name(s, f, spp), frames[s, f, spp])
    _preprocess(tmp_path / "raw", tmp_path / "out", patch_size=2, sequence_frames=2, load_fn=None)
    entry = _index(tmp_path / "out", "full", "test")["shards"][0]
    seq = torch.load(tmp_path / "out" / "full" / "test" / entry["file"], weights_only=True)

    def chw(key, spp):
        return np.stack([frames[entry["scene"], f, spp][key].transpose(2, 0, 1) for f in range(2)])

    np.testing.assert_array_equal(seq["color"].numpy(), chw("color", 2))
    np.testing.assert_array_equal(seq["reference"].numpy(), chw("color", 16))
    np.testing.assert_allclose(seq["target_volume"].numpy(), _lm(chw("volume", 16)), rtol=2e-6)


def test_samples_and_whole_sequences_hold_the_recomputed_arrays(prepared):
    """Every train/val sample is its sequence's arrays at (start + j, corner), every val/test sequence
    the whole arrays, channels first; recomputed here from the synthetic frames."""
    _, out, _ = prepared
    for split in ("train", "val"):
        for entry in _index(out, "patches", split)["shards"]:
            shard = torch.load(out / "patches" / split / entry["file"], weights_only=True)
            want = expected_arrays(entry["scene"], entry["spp"])
            for key, value in want.items():
                for i, (start, (r, c)) in enumerate(zip(shard["starts"], shard["corners"], strict=True)):
                    crop = value[start : start + K, r : r + P, c : c + P]  # (k, P, P, C)
                    np.testing.assert_allclose(
                        shard[key][i].numpy(), np.moveaxis(crop, -1, 1), rtol=2e-6, atol=1e-6, err_msg=key
                    )
    for split in ("val", "test"):
        for entry in _index(out, "full", split)["shards"]:
            seq = torch.load(out / "full" / split / entry["file"], weights_only=True)
            want = expected_arrays(entry["scene"], entry["spp"])
            assert set(seq) == set(want)
            for key, value in want.items():
                np.testing.assert_allclose(seq[key].numpy(), np.moveaxis(value, -1, 1), rtol=2e-6, atol=1e-6)


def test_the_samples_are_drawn_on_the_thesis_importance_of_the_noisy_frames_with_the_defaults(prepared):
    """Each train/val shard's (starts, corners) recomputed here: the thesis map of every noisy frame (colour
    and normals, a window of one patch: 4 -> the odd 5), sampled with the per-sequence generator (seed,
    crc32 of the scene, spp) and the documented defaults (candidates_factor 4, min_keep_prob 0.1,
    min_distance half a patch)."""
    from src.data.patch_sampling import thesis_importance_map
    from src.data.sequence_patches import sample_sequence_patches

    _, out, _ = prepared
    for split in ("train", "val"):
        for entry in _index(out, "patches", split)["shards"]:
            noisy = [synthetic_frame(entry["scene"], f, entry["spp"], H, W) for f in range(FRAMES)]
            imp = np.stack([thesis_importance_map(n["color"], n["normal"], 5) for n in noisy])
            rng = np.random.default_rng([1, zlib.crc32(entry["scene"].encode()), entry["spp"]])
            starts, corners = sample_sequence_patches(imp, P, N, K, rng, 4.0, 0.1, P / 2)
            shard = torch.load(out / "patches" / split / entry["file"], weights_only=True)
            assert torch.equal(shard["starts"], torch.from_numpy(starts)), entry
            assert torch.equal(shard["corners"], torch.from_numpy(corners)), entry


def _shard_inputs(out, split):
    """Every stored sample's `inputs` of one split, as (samples * frames * pixels, 62) float64."""
    parts = []
    for entry in _index(out, "patches", split)["shards"]:
        x = torch.load(out / "patches" / split / entry["file"], weights_only=True)["inputs"].double()
        parts.append(x.movedim(2, -1).reshape(-1, x.shape[2]))  # (n, k, C, P, P) -> (n k P P, C)
    return torch.cat(parts).numpy()


def test_the_whitening_statistics_are_the_train_samples_mean_and_std_per_channel(prepared):
    """Recomputed here in one pass over the four train shards (two scenes x two noisy spp): the streamed
    merge of per-shard moments must give the pooled statistics, of the train samples only."""
    _, out, _ = prepared
    stats = json.loads((out / "whitening.json").read_text())
    assert list(stats) == ["inputs"]
    train = _shard_inputs(out, "train")
    assert train.shape == (4 * N * K * P * P, 62)
    mean, std = train.mean(axis=0), train.std(axis=0)  # population std (ddof 0)
    assert (std > 1e-3).all()
    np.testing.assert_allclose(stats["inputs"]["mean"], mean, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(stats["inputs"]["std"], std, rtol=1e-9, atol=1e-12)
    # The fixture can tell: with the val samples nearly every channel's mean moves; one shard alone differs.
    both = np.concatenate([train, _shard_inputs(out, "val")])
    assert (np.abs(both.mean(axis=0) - mean) > 1e-6 * (1 + np.abs(mean))).mean() > 0.9
    assert np.abs(train[: N * K * P * P].std(axis=0) - std).max() > 1e-2


def test_bad_preprocess_settings_are_one_line_config_errors(tmp_path):
    raw = _raw(tmp_path / "raw", frames=FRAMES, spps=(2, 64))
    cases = [
        (
            dict(sequence_frames=4),
            ["dataset.preprocess.sequence_frames=4 is more than the 3 frame(s)", "'a-0000'"],
        ),
        (dict(importance="random"), ["task.preprocess.importance='random'", "'thesis'", "'mc_variance'"]),
        (dict(volume_transform="log"), ["dataset.preprocess.volume_transform='log'"]),
    ]
    for kw, needles in cases:
        with pytest.raises(ConfigError) as err:
            _preprocess(raw, tmp_path / "out", **kw)
        one_line_error(err, *needles)
    assert not (tmp_path / "out").exists()

    def without_depth(path, buffers):  # one noisy file lacks a buffer: named with its folder, scene, spp
        frame = _load(path, buffers)
        return (
            {k: v for k, v in frame.items() if k != "depth"} if "b-0000-f0001-00002" in path.name else frame
        )

    with pytest.raises(DataError) as err:
        _preprocess(raw, tmp_path / "out", load_fn=without_depth)
    one_line_error(err, f"{raw}: b-0000 2 spp: buffer 'depth' is missing")


def test_whiten_eps_floors_the_stored_std_and_other_settings_reach_the_sampler(tmp_path, capsys):
    """`whiten_eps` 50 is above every channel's spread here: every std is 50. `split_seed`, `importance`,
    `importance_percentile`, `candidates_factor`, `min_keep_prob`, `min_distance` and `sample_seed` are
    passed on: the splits are `split_scenes`' and the positions those of `sample_sequence_patches` on the
    Monte Carlo variance map (six scenes: a split by another seed matches by chance ~1 in 60)."""
    from src.data.patch_sampling import importance_map
    from src.data.sequence_patches import sample_sequence_patches
    from src.data.splits import split_scenes

    scenes = [f"{c}-0000" for c in "abcdef"]
    raw = _raw(tmp_path / "raw", scenes=scenes, frames=FRAMES, spps=(2, 64))
    kw = dict(whiten_eps=50.0, importance="mc_variance", importance_percentile=90.0, candidates_factor=2.0)
    kw |= dict(min_keep_prob=1.0, min_distance=1.0, sample_seed=7, split_seed=5)
    _preprocess(raw, tmp_path / "out", **kw)
    assert capsys.readouterr().err == ""  # progress=False: no bar
    assert json.loads((tmp_path / "out" / "splits.json").read_text()) == split_scenes(scenes, FRACTIONS, 5)
    assert json.loads((tmp_path / "out" / "whitening.json").read_text())["inputs"]["std"] == [50.0] * 62
    assert _shard_inputs(tmp_path / "out", "train").std(axis=0).max() < 50.0
    differs = []  # the fixture can tell min_keep_prob 1 from the default 0.1
    for split in ("train", "val"):
        for entry in _index(tmp_path / "out", "patches", split)["shards"]:
            noisy = [synthetic_frame(entry["scene"], f, 2, H, W) for f in range(FRAMES)]
            maps = [importance_map(n["colorVariance"], n["normalVariance"], percentile=90.0) for n in noisy]
            seed = [7, zlib.crc32(entry["scene"].encode()), 2]
            starts, corners = sample_sequence_patches(
                np.stack(maps), P, N, K, np.random.default_rng(seed), 2.0, 1.0, 1.0
            )
            shard = torch.load(tmp_path / "out" / "patches" / split / entry["file"], weights_only=True)
            assert torch.equal(shard["starts"], torch.from_numpy(starts))
            assert torch.equal(shard["corners"], torch.from_numpy(corners))
            _, default_corners = sample_sequence_patches(
                np.stack(maps), P, N, K, np.random.default_rng(seed), 2.0, 0.1, 1.0
            )
            differs.append(not np.array_equal(corners, default_corners))
    assert any(differs)


def test_one_frame_sequences_are_preprocessed(tmp_path):
    """dataset.frames = 1 (still frames as sequences of one): the sample counts come from the only frame."""
    raw = _raw(tmp_path / "raw", frames=1, spps=(2, 8, 64))
    summary = _preprocess(raw, tmp_path / "out", sequence_frames=1)
    assert summary["noisy_sequences"] == 8 and summary["full_sequences"] == {"val": 2, "test": 2}
    entries = _index(tmp_path / "out", "patches", "train")["shards"]
    assert [(e["spp"], e["reference_spp"], e["frames"]) for e in entries] == [(2, 64, 1), (8, 64, 1)] * 2
    shard = torch.load(tmp_path / "out" / "patches" / "train" / entries[0]["file"], weights_only=True)
    assert shard["inputs"].shape == (N, 1, 62, P, P) and not shard["starts"].any()


def test_the_default_progress_bar_counts_the_noisy_sequences(tmp_path, capsys):
    raw = _raw(tmp_path / "raw", frames=FRAMES, spps=(2, 64))
    preprocess_volume_dataset(
        raw, tmp_path / "out", patch_size=P, patches_per_sequence=N, sequence_frames=K,
        split_fractions=FRACTIONS, split_seed=0, sample_seed=1, load_fn=_load,
    )  # fmt: skip
    err = capsys.readouterr().err
    assert "preprocess volumetric: 100%" in err and " 4/4 " in err and "seq/s]" in err, err


# Surviving mutants of src/data/volume_shards.py (bash scripts/mutation.sh volume_shards), all equivalent
# here:
# - _default_load_fn `buffers=buffers` -> None / dropped: load_volume_exr then reads every buffer of the
#   file, and only the named ones are ever looked up: the same arrays, read more slowly.
# - sequence_arrays' final `np.asarray(v, dtype=np.float32)` -> dtype None / dropped: every array is
#   float32 already (_stack casts each buffer; the transforms and the division by a Python-float distance
#   scale keep float32; test_half_precision_frames_are_stored_as_float32_computed_in_float32).
# - _SequenceWriter.finish `round(seconds, 3)` -> `round(seconds, 4)`: the reported run time to 0.1 ms
#   instead of 1 ms; no test can pin a duration beyond its bounds (0 < seconds <= the caller's clock).
