"""Data never collide: each dataset and profile has its own data folder (conf/config.yaml's
`paths.dataset`), and a render stage leaves its folder holding exactly what the config renders, deleting
only files it rendered itself (src/render/stale_renders.py) and never a user's own."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from src.errors import ConfigError
from src.render.stale_renders import remove_stale_entries, remove_stale_files, remove_stale_scenes
from tests.conftest import compose_config, one_line_error, smoke_config

# --- where each configuration's data go -------------------------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "folder"),
    [
        ([], "procedural"),
        (["dataset=volumetric"], "volumetric"),
        (["task=nerf"], "nerf_procedural"),
    ],
)
def test_every_profile_has_its_own_data_folder(overrides, folder, tmp_path):
    paths = {}
    for profile in ("smoke", "cpu", "paper"):
        cfg = compose_config([f"profile={profile}", f"paths.data={tmp_path}", *overrides])
        paths[profile] = cfg.paths
        assert cfg.paths.dataset == f"{tmp_path}/{folder}/{profile}"
        if folder == "nerf_procedural":
            assert cfg.paths.scenes == f"{tmp_path}/{folder}/{profile}/scenes"
        else:
            assert cfg.paths.raw == f"{tmp_path}/{folder}/{profile}/raw"
            assert cfg.paths.prepared == f"{tmp_path}/{folder}/{profile}/prepared"
    if folder == "volumetric":  # the feature selection is made from (and for) one profile's data
        assert cfg.dataset.feature_selection.dir == f"{tmp_path}/volumetric/paper/feature_selection"


def test_a_users_own_data_stay_where_they_are(tmp_path):
    """`paths.raw=/data/kpcn` and `dataset=blender dataset.root=...` are read in place, whatever the
    profile (what the harness prepares from them still goes to the profile's folder)."""
    cfg = compose_config(["profile=smoke", f"paths.data={tmp_path}", f"paths.raw={tmp_path}/kpcn"])
    assert (
        cfg.paths.raw == f"{tmp_path}/kpcn" and cfg.paths.prepared == f"{tmp_path}/procedural/smoke/prepared"
    )
    nerf = ["profile=smoke", "task=nerf", "dataset=blender", f"dataset.root={tmp_path}/syn"]
    nerf = compose_config([*nerf, f"paths.data={tmp_path}"])
    assert nerf.paths.scenes == f"{tmp_path}/syn"


# --- the render stages delete what they rendered for another config, and only that ------------------------


def _files(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def test_still_images_the_config_no_longer_makes_are_removed(tmp_path, capsys):
    for name in ("a-00004spp.exr", "a-00008spp.exr", "b-00004spp.exr", "mine-00004spp.exr"):
        (tmp_path / name).write_bytes(b"x")
    # c's file is already gone (deleted by hand, or by another job): its entry goes all the same
    rendered = {
        "a-00004spp.exr": "k1",
        "a-00008spp.exr": "k2",
        "b-00004spp.exr": "k3",
        "c-00004spp.exr": "k4",
    }
    (tmp_path / "manifest.json").write_text(json.dumps(rendered))
    removed = remove_stale_files(tmp_path, {"a-00004spp.exr", "a-00016spp.exr"})
    assert removed == ["a-00008spp.exr", "b-00004spp.exr", "c-00004spp.exr"]
    # the user's file (not in the manifest) stays; the manifest keeps only what stays
    assert _files(tmp_path) == ["a-00004spp.exr", "manifest.json", "mine-00004spp.exr"]
    assert json.loads((tmp_path / "manifest.json").read_text()) == {"a-00004spp.exr": "k1"}
    assert capsys.readouterr().out == (
        f"render: removed 3 earlier render(s) the config no longer makes from {tmp_path}: "
        "a-00008spp.exr, b-00004spp.exr, c-00004spp.exr\n"
    )
    # nothing to remove: nothing printed, nothing rewritten
    assert remove_stale_files(tmp_path, {"a-00004spp.exr"}) == []
    assert capsys.readouterr().out == ""


def test_a_long_list_of_removed_files_is_shortened(tmp_path, capsys):
    names = [f"s{i}-00004spp.exr" for i in range(5)]
    (tmp_path / "manifest.json").write_text(json.dumps(dict.fromkeys(names, "k")))
    assert remove_stale_files(tmp_path, set()) == names
    assert capsys.readouterr().out == (
        f"render: removed 5 earlier render(s) the config no longer makes from {tmp_path}: "
        "s0-00004spp.exr, s1-00004spp.exr, s2-00004spp.exr, s3-00004spp.exr, ... (5 in all)\n"
    )
    (tmp_path / "manifest.json").write_text(json.dumps(dict.fromkeys(names[:4], "k")))
    remove_stale_files(tmp_path, set())
    assert capsys.readouterr().out.endswith(
        ": s0-00004spp.exr, s1-00004spp.exr, s2-00004spp.exr, s3-00004spp.exr\n"
    )


def test_a_folder_without_a_manifest_is_a_users_and_is_left_alone(tmp_path):
    (tmp_path / "scene-00004spp.exr").write_bytes(b"x")
    assert remove_stale_files(tmp_path, set()) == []
    assert remove_stale_entries(tmp_path, "manifest", set()) == []
    assert _files(tmp_path) == ["scene-00004spp.exr"]


def test_volumetric_files_the_dataset_no_longer_has_are_removed(tmp_path):
    entries = tmp_path / "manifest"
    entries.mkdir()
    for name in ("s-f0000-00004spp.exr", "s-f0001-00004spp.exr", "s-f0002-00004spp.exr"):
        (tmp_path / name).write_bytes(b"x")
        (entries / f"{name}.json").write_text("{}")
    (tmp_path / "mine-f0000-00004spp.exr").write_bytes(b"x")  # no entry: a user's
    # another job's entry being written (src/io/atomic.py's temporary name): not a file of ours yet
    (entries / ".s-f0009-00004spp.exr.json.tmp-12-ab12cd34.json").write_text("{}")
    (entries / "gone-f0000-00004spp.exr.json").write_text("{}")  # an entry whose file is already gone
    removed = remove_stale_entries(tmp_path, "manifest", {"s-f0000-00004spp.exr", "s-f0001-00004spp.exr"})
    assert removed == ["gone-f0000-00004spp.exr", "s-f0002-00004spp.exr"]
    assert _files(tmp_path) == [
        "manifest/.s-f0009-00004spp.exr.json.tmp-12-ab12cd34.json",
        "manifest/s-f0000-00004spp.exr.json",
        "manifest/s-f0001-00004spp.exr.json",
        "mine-f0000-00004spp.exr",
        "s-f0000-00004spp.exr",
        "s-f0001-00004spp.exr",
    ]


def test_jobs_removing_the_same_stale_entry_at_once_all_succeed(tmp_path, monkeypatch, capsys):
    """Fanned-out volumetric render jobs start together and each removes the same stale files: a job may
    find an entry it listed already deleted by another."""
    entries = tmp_path / "manifest"
    entries.mkdir()
    (entries / "old-f0000-00004spp.exr.json").write_text("{}")
    glob = Path.glob

    def glob_seeing_a_vanished_entry(self, pattern):
        return [*glob(self, pattern), self / "taken-f0000-00004spp.exr.json"]

    monkeypatch.setattr(Path, "glob", glob_seeing_a_vanished_entry)
    removed = remove_stale_entries(tmp_path, "manifest", set())
    assert removed == ["old-f0000-00004spp.exr", "taken-f0000-00004spp.exr"] and not any(entries.iterdir())
    assert (
        f"removed 2 earlier render(s) the config no longer makes from {tmp_path}: old-"
        in capsys.readouterr().out
    )


def test_multiview_scenes_the_config_no_longer_lists_are_removed(tmp_path, capsys):
    for name in ("spheres", "busy", ".tabletop.tmp-12-ab12cd34", "lego"):
        (tmp_path / name).mkdir()
        (tmp_path / name / "transforms_train.json").write_text("{}")
    for name in ("spheres", "busy", ".tabletop.tmp-12-ab12cd34"):  # ours; lego is a user's
        (tmp_path / name / "nrbench_render.json").write_text("{}")
    assert remove_stale_scenes(tmp_path, "nrbench_render.json", ["spheres", "tabletop"]) == ["busy"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".tabletop.tmp-12-ab12cd34", "lego", "spheres"]
    assert (
        f"removed 1 earlier render(s) the config no longer makes from {tmp_path}: busy"
        in capsys.readouterr().out
    )


# --- the sequence: smoke, then cpu, then smoke, in one data folder ----------------------------------

#: The `cpu` profile at a few seconds' size: another frame size and other sample counts than smoke's.
SMALL_CPU = [
    "profile=cpu",
    "dataset.width=40",
    "dataset.height=24",
    "dataset.scenes_per_base=1",
    "dataset.noisy_spp=[4,8]",
    "dataset.reference_spp=64",
    "dataset.randomize.env_res=16",
    "dataset.randomize.texture_res=32",
    "task.preprocess.patch_size=8",
    "dataset.preprocess.patches_per_image=6",
]


def _render_and_preprocess(data, overrides):
    from src.stages import preprocess, render

    cfg = smoke_config(data, data / "run", overrides)
    render(cfg)
    return cfg, preprocess(cfg)


@pytest.mark.slow
def test_smoke_then_cpu_then_smoke_in_one_data_folder(tmp_path, mitsuba_variant, capsys):
    """~10 s. Before the data folders were per profile, the cpu preprocess read smoke's 48x32 renders
    beside its own 40x24 ones and stopped on the size mismatch. An override within a profile (another
    frame size and other sample counts) must not collide either, and switching back renders nothing
    that is still current."""
    smoke, first = _render_and_preprocess(tmp_path, [])
    raw = Path(smoke.paths.raw)
    smoke_raw = {p.name: p.stat().st_mtime_ns for p in raw.iterdir()}
    cpu, summary = _render_and_preprocess(tmp_path, SMALL_CPU)
    assert cpu.paths.raw != smoke.paths.raw and summary["noisy_images"] == 3 * 2
    again, _ = _render_and_preprocess(tmp_path, [])
    out = capsys.readouterr().out
    assert out.count("render: all 9 files up to date") == 1 and out.count("preprocess: up to date") == 1
    assert {p.name: p.stat().st_mtime_ns for p in raw.iterdir()} == smoke_raw
    # Within one profile: smoke with cpu's sizes, then plain smoke again.
    _, within = _render_and_preprocess(tmp_path, SMALL_CPU[1:])
    assert within["noisy_images"] == 3 * 2
    _, back = _render_and_preprocess(tmp_path, [])
    assert back["noisy_images"] == first["noisy_images"] == 3 * 2
    names = [f"{b}-0000-{spp:05d}spp.exr" for b in ("cornell", "outdoor", "tabletop") for spp in (4, 16, 128)]
    assert sorted(p.name for p in raw.glob("*.exr")) == names
    assert sorted(json.loads((raw / "manifest.json").read_text())) == names
    # A stage=train after them with other preprocessing settings stops at job start (prepared_check.py).
    from src.stages import task_of

    task_of(smoke).check_stages(["train"], smoke)
    other = smoke_config(tmp_path, tmp_path / "run", ["task.preprocess.patch_size=16"])
    with pytest.raises(ConfigError) as excinfo:
        task_of(other).check_stages(["train"], other)
    one_line_error(excinfo, "procedural/smoke/prepared:", "task.preprocess", "run stage=preprocess")
