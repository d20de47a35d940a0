"""Scene splits, file naming, shard streaming across workers and the preprocess stage end to end."""

import json
import zlib

import numpy as np
import pytest
import torch
from torch.utils.data import DataLoader

from src.data.denoise_dataset import FullImageDataset, PatchShardDataset
from src.data.features import PAPER_CHANNELS
from src.data.kpcn_preprocess import compute_whitening_stats, load_whitening_stats
from src.data.shards import (
    GP_SHARD_KEYS,
    SAMPLING_FIGURE,
    SHARD_CHANNELS,
    SHARD_KEYS,
    load_tensors,
    preprocess_dataset,
    read_index,
    save_tensors,
)
from src.data.splits import base_scene, group_dataset, parse_exr_name, patch_quota, split_scenes
from src.data.transforms import rebuild_color
from src.errors import ConfigError, DataError
from src.io.atomic import atomic_write_json
from tests.conftest import one_line_error

FRACTIONS = {"train": 0.5, "val": 0.25, "test": 0.25}


def test_parse_exr_name():
    assert parse_exr_name("/x/cornell-0003-00016spp.exr") == ("cornell-0003", 16)
    assert parse_exr_name("a-04096spp.exr") == ("a", 4096)
    for bad in ("cornell.exr", "cornell-16.exr", "-00016spp.exr", "c-00016spp.png", "c-00000spp.exr"):
        with pytest.raises(DataError) as excinfo:
            parse_exr_name(f"/x/{bad}")
        one_line_error(excinfo, bad, "expected a file name like '<scene>-00016spp.exr'")


def test_split_scenes_disjoint_covering_deterministic():
    names = [f"scene-{i:02d}" for i in range(11)]
    s = split_scenes(reversed(names), FRACTIONS, seed=3)
    assert s == split_scenes(names, FRACTIONS, seed=3)
    assert s != split_scenes(names, FRACTIONS, seed=4)
    assert sorted(sum(s.values(), [])) == names and all(s[k] for k in s)
    assert len(s["train"]) > len(s["val"])
    three = split_scenes(["a", "b", "c"], {"train": 0.9, "val": 0.05, "test": 0.05}, 0)
    assert all(len(v) == 1 for v in three.values())
    with pytest.raises(ConfigError) as excinfo:
        split_scenes(["a", "b"], FRACTIONS, 0)
    one_line_error(excinfo, "task.preprocess.split", "at least 3 scenes", "got 2: ['a', 'b']")
    with pytest.raises(ConfigError) as excinfo:
        split_scenes(names, {"train": 1.0, "val": 0.0, "test": 0.0}, 0)
    one_line_error(excinfo, "task.preprocess.split=", "'val': 0.0", "expected every fraction finite and > 0")
    with pytest.raises(ConfigError) as excinfo:
        split_scenes(names, {"train": 1.0, "valid": 0.5, "test": 0.5}, 0)
    one_line_error(excinfo, "task.preprocess.split", "'valid'", "expected the keys ['train', 'val', 'test']")


def test_group_dataset(tmp_path):
    with pytest.raises(DataError) as excinfo:
        group_dataset(tmp_path)
    one_line_error(excinfo, str(tmp_path), "no '<scene>-<NNNNN>spp.exr' files found")
    for name in ("a-b-00004spp.exr", "a-b-00064spp.exr", "c-00008spp.exr", "notes.txt"):
        (tmp_path / name).touch()
    with pytest.raises(DataError) as excinfo:
        group_dataset(tmp_path)
    one_line_error(excinfo, "'c'", "single sample count")
    (tmp_path / "c-01024spp.exr").touch()
    g = group_dataset(tmp_path)
    assert list(g) == ["a-b", "c"] and list(g["c"]) == [8, 1024]
    assert g["a-b"][64].name == "a-b-00064spp.exr"


def test_shards_stream_every_patch_once_per_epoch_with_two_workers(tmp_path):
    root, sizes, entries, pid = tmp_path / "patches" / "train", [5, 3, 7, 1, 4], [], 0
    for i, n in enumerate(sizes):
        shard = {k: torch.zeros(n, 3, 4, 4) for k in SHARD_KEYS}
        ids = torch.arange(pid, pid + n, dtype=torch.float32).view(n, 1, 1, 1)
        shard["diffuse_in"] = shard["specular_in"] = ids.expand(n, 38, 4, 4)
        save_tensors(root / f"s{i}.pt", shard)
        entries.append({"file": f"s{i}.pt", "scene": f"s{i}", "spp": 4, "n_patches": n})
        pid += n
    channels = {k: list(v) for k, v in SHARD_CHANNELS.items()}
    atomic_write_json(root / "index.json", {"patch_size": 4, "channels": channels, "shards": entries})
    ds = PatchShardDataset(tmp_path, "train", seed=1)
    assert len(ds) == sum(sizes)
    orders = []
    for epoch in (0, 1):
        ds.set_epoch(epoch)
        ids = torch.cat([b["diffuse_in"][:, 0, 0, 0] for b in DataLoader(ds, batch_size=3, num_workers=2)])
        assert sorted(ids.long().tolist()) == list(range(sum(sizes)))
        assert next(iter(DataLoader(ds, batch_size=4)))["diffuse_t"].shape == (4, 3, 4, 4)
        orders.append(ids.tolist())
    assert orders[0] != orders[1]


def test_a_shard_stream_yields_each_shards_rows_in_its_own_permutation():
    """`ShardStream` (one worker): the shards in `worker_shard_order`, and the rows of shard i in the order
    of `default_rng([seed, epoch, i]).permutation`, so two equal-sized shards are shuffled differently;
    without `shuffle`, shards and rows in stored order."""
    import numpy as np

    from src.data.denoise_dataset import ShardStream, worker_shard_order

    class Stream(ShardStream):
        def __init__(self, shuffle):  # no index file: the shards as ShardStream.__init__ would set them
            self.shards, self.seed, self.shuffle, self.epoch = [{}, {}, {}], 7, shuffle, 0

        def _load_shard(self, i):
            return {"color": torch.arange(5) + 10 * int(i)}

    stream = Stream(shuffle=True)
    stream.set_epoch(3)
    want = [
        10 * int(i) + j
        for i in worker_shard_order(3, 7, 3, True)
        for j in np.random.default_rng([7, 3, int(i)]).permutation(5)
    ]
    got = [int(row["color"]) for row in stream]
    assert got == want
    assert [g % 10 for g in got[:5]] != [g % 10 for g in got[5:10]]
    assert [int(row["color"]) for row in Stream(shuffle=False)] == [
        0,
        1,
        2,
        3,
        4,
        10,
        11,
        12,
        13,
        14,
        20,
        21,
        22,
        23,
        24,
    ]


def synthetic_image(scene, spp, h=24, w=40):
    """Buffers for a scene (fixed per scene) with noise shrinking with spp; deterministic."""
    base = np.random.default_rng(sum(map(ord, scene)))
    noise = np.random.default_rng([sum(map(ord, scene)), spp])
    f = lambda rng, c: rng.random((h, w, c), dtype=np.float32)  # noqa: E731
    albedo, irr, spec = 0.1 + 0.8 * f(base, 3), 0.5 + f(base, 3), 2 * f(base, 3) ** 3
    n = 1 / np.sqrt(spp)
    diffuse = albedo * irr * (1 + n * (f(noise, 3) - 0.5))
    specular = spec * (1 + n * (f(noise, 3) - 0.5))
    b = {"diffuse": diffuse, "specular": specular, "color": diffuse + specular, "albedo": albedo}
    b.update(normal=f(base, 3), depth=1 + f(base, 1), visibility=f(base, 1))
    for k in ("color", "diffuse", "specular", "albedo", "normal", "depth", "visibility"):
        b[f"{k}Variance"] = n * f(noise, 1)
    return b


def _preprocess(raw, out, load_fn, **kw):
    return preprocess_dataset(
        raw, out, eps=0.00316, patch_size=8, patches_per_image=6, split_fractions=FRACTIONS, split_seed=0,
        sample_seed=1, candidates_factor=4, min_keep_prob=0.1, min_distance=None, whiten_eps=1e-4,
        load_fn=load_fn, progress=False, **kw,
    )  # fmt: skip


def test_patch_quota_spreads_a_split_total_evenly():
    assert patch_quota(32, 13494) == [422] * 22 + [421] * 10
    assert sum(patch_quota(8, 3373)) == 3373 and max(patch_quota(8, 3373)) - min(patch_quota(8, 3373)) == 1
    with pytest.raises(ConfigError) as excinfo:
        patch_quota(0, 5)
    one_line_error(excinfo, "dataset.preprocess.patches_per_split", "no images")


def _synthetic_raw(tmp_path, scenes, spps=(4, 16, 1024)):
    raw = tmp_path / "raw"
    raw.mkdir()
    for s in scenes:
        for spp in spps:
            (raw / f"{s}-{spp:05d}spp.exr").touch()
    return raw


def _load_synthetic(path):
    return synthetic_image(*parse_exr_name(path))


def test_patches_per_split_fixes_each_split_s_patch_count(tmp_path):
    """The thesis's budget is a patch count per split (16,867 split 80/20), not a count per image."""
    raw = _synthetic_raw(tmp_path, ["a", "b", "c", "d", "e"])
    summary = _preprocess(raw, tmp_path / "out", _load_synthetic, patches_per_split={"train": 11, "val": 3})
    assert summary["patches"] == {"train": 11, "val": 3}
    counts = [e["n_patches"] for e in PatchShardDataset(tmp_path / "out", "train").shards]
    assert sum(counts) == 11 and max(counts) - min(counts) <= 1


def test_preprocess_dataset_end_to_end(tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    scenes = ["box-a", "box-b", "room", "glossy-1"]
    for s in scenes:
        for spp in (4, 16, 1024):
            (raw / f"{s}-{spp:05d}spp.exr").touch()

    def load_fn(path):
        scene, spp = parse_exr_name(path)
        return synthetic_image(scene, spp)

    summary = _preprocess(raw, tmp_path / "out", load_fn)
    out = tmp_path / "out"
    splits = json.loads((out / "splits.json").read_text())
    assert sorted(sum(splits.values(), [])) == sorted(scenes)
    assert {k: len(v) for k, v in splits.items()} == {"train": 2, "val": 1, "test": 1}
    assert summary["patches"] == {"train": 2 * 2 * 6, "val": 1 * 2 * 6}
    assert summary == json.loads((out / "summary.json").read_text())
    assert summary["settings"]["importance"] == "thesis"
    figure = (out / SAMPLING_FIGURE).read_bytes()  # importance map | candidates | kept, first train image
    assert figure.startswith(b"\x89PNG") and len(figure) > 5000
    assert not list(out.glob(".*tmp*"))

    train = PatchShardDataset(out, "train")
    batch = next(iter(DataLoader(train, batch_size=24)))
    assert batch["diffuse_in"].shape == (24, 28, 8, 8) and batch["diffuse_in"].dtype == torch.float32
    assert {e["scene"] for e in train.shards} == set(splits["train"])
    assert {e["scene"] for e in PatchShardDataset(out, "val").shards} == set(splits["val"])
    back = rebuild_color(batch["diffuse_target"], batch["specular_target"], batch["albedo"], 0.00316)
    torch.testing.assert_close(back, batch["reference"], rtol=1e-5, atol=1e-5)

    test = FullImageDataset(out, "test")
    assert len(test) == 2 and test[0]["scene"] == splits["test"][0] and test[0]["color"].shape == (3, 24, 40)
    assert len(FullImageDataset(out, "val")) == 2
    with pytest.raises(DataError) as excinfo:
        PatchShardDataset(out, "test")
    one_line_error(excinfo, str(out / "patches" / "test"), "index")

    # whitening: train patches only; held-out scenes scaled wildly change nothing
    stats = load_whitening_stats(out / "whitening.json")
    shards = [torch.load(out / "patches/train" / e["file"]) for e in train.shards]
    direct = compute_whitening_stats((s["specular_in"].permute(0, 2, 3, 1).numpy() for s in shards), 1e-4)
    np.testing.assert_allclose(stats["specular_in"].mean, direct.mean, rtol=1e-6)

    def wild_load_fn(path):
        scene, spp = parse_exr_name(path)
        b = synthetic_image(scene, spp)
        return b if scene in splits["train"] else {k: v * 1e3 for k, v in b.items()}

    _preprocess(raw, tmp_path / "out2", wild_load_fn)
    assert (out / "whitening.json").read_text() == (tmp_path / "out2/whitening.json").read_text()
    again = torch.load(tmp_path / "out2/patches/train" / train.shards[0]["file"])
    torch.testing.assert_close(again["diffuse_in"], shards[0]["diffuse_in"], rtol=0, atol=0)

    whitened = next(
        iter(DataLoader(PatchShardDataset(out, "train", whitening=out / "whitening.json"), batch_size=24))
    )
    assert whitened["diffuse_in"][:, 3:].mean().abs() < 1

    # task.features: the configured channels, by name, from the stored candidates; whitening alike
    features = ["visibility", "visibility.grad", "albedo", "color.var"]
    names = [
        "visibility",
        "visibility_dx_v",
        "visibility_dy_v",
        "albedo_r",
        "albedo_g",
        "albedo_b",
        "color_var",
    ]
    stored = list(SHARD_CHANNELS["diffuse_in"])
    picked = [stored.index(n) for n in names]
    plain = next(
        iter(DataLoader(PatchShardDataset(out, "train", shuffle=False, features=features), batch_size=6))
    )
    torch.testing.assert_close(plain["diffuse_in"], shards[0]["diffuse_in"][:, picked], rtol=0, atol=0)
    torch.testing.assert_close(plain["diffuse_t"], shards[0]["diffuse_in"][:, :3], rtol=0, atol=0)
    white = PatchShardDataset(out, "train", features=features, whitening=out / "whitening.json")
    np.testing.assert_array_equal(white.whitening["specular_in"].std, stats["specular_in"].std[picked])
    item = FullImageDataset(out, "test", features=features)[0]
    assert item["specular_in"].shape == (len(names), 24, 40)
    paper = next(iter(DataLoader(PatchShardDataset(out, "train", shuffle=False), batch_size=6)))
    torch.testing.assert_close(  # the default is the paper's 28, in the order of Bako et al.
        paper["diffuse_in"], shards[0]["diffuse_in"][:, [stored.index(n) for n in PAPER_CHANNELS]]
    )


def test_preprocess_importance_option_changes_the_patches_and_rejects_unknown_names(tmp_path):
    raw = tmp_path / "raw"
    raw.mkdir()
    for s in ("a", "b", "c"):
        for spp in (4, 1024):
            (raw / f"{s}-{spp:05d}spp.exr").touch()

    def load_fn(path):
        return synthetic_image(*parse_exr_name(path))

    corners = {}
    for kind in ("thesis", "mc_variance"):
        summary = _preprocess(raw, tmp_path / kind, load_fn, importance=kind, importance_window=0.5)
        assert summary["settings"]["importance"] == kind and (tmp_path / kind / SAMPLING_FIGURE).is_file()
        entry = json.loads((tmp_path / kind / "patches/train/index.json").read_text())["shards"][0]
        corners[kind] = torch.load(tmp_path / kind / "patches/train" / entry["file"])["corners"]
    assert not torch.equal(corners["thesis"], corners["mc_variance"])
    with pytest.raises(ConfigError) as excinfo:
        _preprocess(raw, tmp_path / "bad", load_fn, importance="bako")
    one_line_error(excinfo, "task.preprocess.importance='bako'", "'mc_variance'")


def _with_gp_features(buffers, scene, spp):
    """`synthetic_image` plus the GP filters' buffers (world position, secondary albedo, their variances)."""
    rng = np.random.default_rng([zlib.crc32(scene.encode()), spp, 7])
    h, w = buffers["color"].shape[:2]
    return {
        **buffers,
        "position": rng.normal(size=(h, w, 3)).astype(np.float32) * 5,
        "positionVariance": rng.uniform(0, 0.1, (h, w, 1)).astype(np.float32),
        "secondary_albedo": rng.uniform(0, 1, (h, w, 3)).astype(np.float32),
        "secondary_albedoVariance": rng.uniform(0, 0.01, (h, w, 1)).astype(np.float32),
    }


def test_preprocess_stores_the_gp_features_when_the_raw_files_have_them(tmp_path):
    """Position, secondary albedo and their variances go into patches and full images unchanged (the GP
    filter normalises them); files without them (real KPCN data) give shards without those keys; a mix is
    a one-line error. The datasets also expose the one-channel guides the GP filter reads by name."""
    raw = _synthetic_raw(tmp_path, ["a", "b", "c", "d"])

    def load_fn(path):
        scene, spp = parse_exr_name(path)
        return _with_gp_features(synthetic_image(scene, spp), scene, spp)

    summary = _preprocess(raw, tmp_path / "gp", load_fn)
    assert summary["gp_features"] == list(GP_SHARD_KEYS)
    full = FullImageDataset(tmp_path / "gp", "test")
    item = full[0]
    expected = load_fn(raw / f"{item['scene']}-{item['spp']:05d}spp.exr")
    np.testing.assert_array_equal(item["position"].numpy(), np.moveaxis(expected["position"], -1, 0))
    np.testing.assert_array_equal(
        item["secondary_albedo_var"].numpy(), np.moveaxis(expected["secondary_albedoVariance"], -1, 0)
    )
    assert item["position_var"].shape == (1, *item["color"].shape[1:])
    # the noisy colour's variance of the pixel mean as rendered (linear; the GP terminal colorVariance),
    # not the diffuse branch's transformed `color_var` input channel
    np.testing.assert_array_equal(item["color_var"].numpy(), np.moveaxis(expected["colorVariance"], -1, 0))
    assert expected["colorVariance"].std() > 0
    stored = full.index["channels"]["diffuse_in"]
    for key in ("visibility", "normal_var", "albedo_var", "depth_var", "visibility_var"):
        torch.testing.assert_close(
            item[key],
            load_tensors(full.root / full.images[0]["file"])["diffuse_in"][
                stored.index(key) : stored.index(key) + 1
            ],
        )
    assert full.index["channels"]["position"] == ["x", "y", "z"]
    patch = next(iter(PatchShardDataset(tmp_path / "gp", "train")))
    assert patch["position"].shape == (3, 8, 8) and patch["secondary_albedo"].shape == (3, 8, 8)

    plain = _preprocess(raw, tmp_path / "plain", _load_synthetic)
    assert plain["gp_features"] == []
    item = FullImageDataset(tmp_path / "plain", "test")[0]
    assert not set(GP_SHARD_KEYS) & set(item) and "visibility" in item and "color_var" in item
    assert "position" not in read_index(tmp_path / "plain" / "full" / "test")["channels"]

    def mixed(path):
        scene, spp = parse_exr_name(path)
        return load_fn(path) if scene == "a" else synthetic_image(scene, spp)

    with pytest.raises(DataError) as excinfo:
        _preprocess(raw, tmp_path / "mixed", mixed)
    one_line_error(excinfo, "GP features", "in all its noisy files or in none")


def test_split_by_base_deals_held_out_scenes_over_the_base_scenes():
    """The plain shuffle of 12 scenes (3 bases x 4, seed 0) puts both test scenes in `outdoor`; dealt
    round-robin over the bases, val keeps its two scenes and test holds two bases. By value, so that a
    change of either rule shows."""
    names = [f"{b}-{i:04d}" for b in ("cornell", "outdoor", "tabletop") for i in range(4)]
    fractions = {"train": 0.7, "val": 0.15, "test": 0.15}
    plain = split_scenes(names, fractions, 0)
    assert plain["val"] == ["cornell-0002", "tabletop-0001"]
    assert plain["test"] == ["outdoor-0000", "outdoor-0003"]  # today's split: one base scene
    dealt = split_scenes(names, fractions, 0, by_base=True)
    assert dealt["val"] == ["cornell-0002", "tabletop-0001"]
    assert dealt["test"] == ["outdoor-0003", "tabletop-0003"]
    assert sorted(sum(dealt.values(), [])) == sorted(names)
    # a user scene file (no -NNNN suffix) is its own base; with more held-out scenes than bases every
    # base appears
    many = split_scenes([*names, "my-scene"], {"train": 0.4, "val": 0.3, "test": 0.3}, 1, by_base=True)
    assert len(many["test"]) == 4 and {n.split("-")[0] for n in many["test"]} >= {
        "cornell",
        "outdoor",
        "tabletop",
    }
    assert base_scene("my-scene") == "my-scene" and base_scene("fog_objects-0012") == "fog_objects"


def _filter_search_profiles():
    """(dataset, profile) of every task=filter_search combination scripts/resolved_configs.py checks."""
    import importlib.util

    from tests.conftest import ROOT

    spec = importlib.util.spec_from_file_location(
        "resolved_configs", ROOT / "scripts" / "resolved_configs.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    pairs = []
    for _, overrides in module.combinations():
        choice = dict(o.split("=", 1) for o in overrides[:4])
        if choice["task"] == "filter_search" and (choice["dataset"], choice["profile"]) not in pairs:
            pairs.append((choice["dataset"], choice["profile"]))
    return pairs


@pytest.mark.parametrize(("dataset", "profile"), _filter_search_profiles())
def test_filter_search_holds_out_scenes_of_at_least_two_base_scenes(dataset, profile):
    """The filter studies' held-out split (task.eval.split of task=filter_search) at every dataset and
    profile: its scenes, as the config's dataset names them and its preprocess splits them, come from
    two base scenes or more, so one image cannot carry a held-out result (issue 32)."""
    from omegaconf import OmegaConf

    from src.render.render_dataset import scene_sources
    from tests.conftest import compose_config

    cfg = compose_config(["task=filter_search", f"dataset={dataset}", f"profile={profile}"])
    ds = OmegaConf.to_container(cfg.dataset) | {"seed": 0}  # names do not depend on the seed
    names = [s.name for s in scene_sources(ds)]
    p = cfg.task.preprocess
    splits = split_scenes(names, dict(p.split), 0, bool(p.split_by_base))  # data_seed's default
    held_out = splits[cfg.task.eval.split]
    assert len({base_scene(n) for n in held_out}) >= 2, (dataset, profile, held_out)
    assert cfg.task.search.split != cfg.task.eval.split


def test_split_by_base_off_keeps_the_prepared_cache_key_and_on_changes_it(tmp_path):
    """Folders the denoise task prepared before the option existed stay valid (its key without the key
    equals its key with `false`); the filter search's `true` makes its own."""
    from omegaconf import OmegaConf, open_dict

    from tests.conftest import compose_config, data_kind

    cfg = compose_config([])
    kind = data_kind(cfg)

    def preprocess_key(config, raw):
        return kind.preprocess_key(config, raw)

    assert cfg.task.preprocess.split_by_base is False
    off = preprocess_key(cfg, tmp_path)
    before = cfg.copy()
    with open_dict(before.task.preprocess):
        del before.task.preprocess["split_by_base"]
    assert preprocess_key(before, tmp_path) == off
    OmegaConf.update(cfg, "task.preprocess.split_by_base", True)
    assert preprocess_key(cfg, tmp_path) != off
