"""Data never collide: each dataset and profile has its own data folder (conf/config.yaml's
`paths.dataset`), and a render stage leaves its folder holding exactly what the config renders, setting
aside into `.parked/` only files it rendered itself (src/render/stale_renders.py) and never a user's own;
two configs sharing a folder (the filter search's smoke data and the denoise task's) do not render each
other's files again."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from src.errors import ConfigError
from src.provenance import data_fingerprint
from src.render.stale_renders import (
    PARK_DAYS,
    expire_parked,
    remove_stale_entries,
    remove_stale_files,
    remove_stale_scenes,
    restore_entry,
    restore_file,
)
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


# --- the render stages set aside what they rendered for another config, and only that ---------------------


def _files(folder):
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if p.is_file())


def _set_aside(folder, count):
    return f"render: set aside {count} render(s) this config does not make, for another config that may"


def test_still_images_the_config_does_not_make_are_set_aside(tmp_path, capsys):
    for name in ("a-00004spp.exr", "a-00008spp.exr", "b-00004spp.exr", "mine-00004spp.exr"):
        (tmp_path / name).write_bytes(name.encode())
    # c's file is already gone (deleted by hand, or by another job): its entry goes all the same
    rendered = {
        "a-00004spp.exr": "k1",
        "a-00008spp.exr": "k2",
        "b-00004spp.exr": "k3",
        "c-00004spp.exr": "k4",
    }
    (tmp_path / "manifest.json").write_text(json.dumps(rendered))
    fingerprint_before = data_fingerprint(tmp_path)
    removed = remove_stale_files(tmp_path, {"a-00004spp.exr", "a-00016spp.exr"}, now=1000.0)
    assert removed == ["a-00008spp.exr", "b-00004spp.exr", "c-00004spp.exr"]
    # the user's file (not in the manifest) stays; the manifest keeps only what stays; the others are
    # parked with their keys (c's, gone, is not)
    assert _files(tmp_path) == [
        ".parked/a-00008spp.exr",
        ".parked/b-00004spp.exr",
        ".parked/entries/a-00008spp.exr.json",
        ".parked/entries/b-00004spp.exr.json",
        "a-00004spp.exr",
        "manifest.json",
        "mine-00004spp.exr",
    ]
    assert json.loads((tmp_path / "manifest.json").read_text()) == {"a-00004spp.exr": "k1"}
    assert json.loads((tmp_path / ".parked/entries/b-00004spp.exr.json").read_text()) == {
        "key": "k3",
        "parked_at": 1000.0,
        "entry": None,
    }
    out = capsys.readouterr().out
    assert out.startswith(_set_aside(tmp_path, 3))
    assert out.endswith(f"into {tmp_path}/.parked: a-00008spp.exr, b-00004spp.exr, c-00004spp.exr\n")
    # what the folder holds for this config is what the fingerprint sees: .parked/ is not part of it
    assert data_fingerprint(tmp_path) != fingerprint_before
    (tmp_path / ".parked").rename(tmp_path.parent / "parked-elsewhere")
    fingerprint_without = data_fingerprint(tmp_path)
    (tmp_path.parent / "parked-elsewhere").rename(tmp_path / ".parked")
    assert data_fingerprint(tmp_path) == fingerprint_without
    # nothing to set aside: nothing printed, nothing rewritten
    assert remove_stale_files(tmp_path, {"a-00004spp.exr"}, now=1000.0) == []
    assert capsys.readouterr().out == ""


def test_a_parked_still_image_comes_back_only_with_the_key_the_config_wants(tmp_path):
    (tmp_path / "b-00004spp.exr").write_bytes(b"b")
    (tmp_path / "manifest.json").write_text(json.dumps({"b-00004spp.exr": "k3"}))
    remove_stale_files(tmp_path, set())
    manifest = {}
    # another key (another frame size, say): not this file; it stays parked, and the caller renders
    assert not restore_file(tmp_path, "b-00004spp.exr", "other", manifest)
    assert manifest == {} and (tmp_path / ".parked/b-00004spp.exr").is_file()
    assert not restore_file(tmp_path, "never-00004spp.exr", "k3", manifest)  # never parked
    assert restore_file(tmp_path, "b-00004spp.exr", "k3", manifest)
    assert (tmp_path / "b-00004spp.exr").read_bytes() == b"b" and manifest == {"b-00004spp.exr": "k3"}
    assert json.loads((tmp_path / "manifest.json").read_text()) == manifest
    assert _files(tmp_path) == ["b-00004spp.exr", "manifest.json"]
    assert not restore_file(tmp_path, "b-00004spp.exr", "k3", manifest)  # moved back once


def test_parked_renders_unused_for_park_days_are_deleted(tmp_path, capsys):
    names = ["old-00004spp.exr", "new-00004spp.exr"]
    day = 86400.0
    for name, when in zip(names, (0.0, 2 * day), strict=True):
        (tmp_path / name).write_bytes(b"x")
        (tmp_path / "manifest.json").write_text(json.dumps({name: "k"}))
        remove_stale_files(tmp_path, set(), now=when)
    (tmp_path / ".parked" / "orphan-00004spp.exr").write_bytes(b"x")  # a park interrupted before its entry
    capsys.readouterr()
    # PARK_DAYS after the first was parked: the second is a day younger than that and stays
    assert expire_parked(tmp_path, now=PARK_DAYS * day + 1) == ["old-00004spp.exr", "orphan-00004spp.exr"]
    assert _files(tmp_path) == [
        ".parked/entries/new-00004spp.exr.json",
        ".parked/new-00004spp.exr",
        "manifest.json",
    ]
    assert capsys.readouterr().out.startswith(
        f"render: deleted 2 render(s) set aside more than {PARK_DAYS} days ago and not needed since from "
        f"{tmp_path}/.parked: old-00004spp.exr, orphan-00004spp.exr"
    )
    assert expire_parked(tmp_path, now=PARK_DAYS * day + 1) == []
    # every render of the folder expires the park first
    remove_stale_files(tmp_path, set(), now=(PARK_DAYS + 2) * day + 1)
    assert _files(tmp_path) == ["manifest.json"]


def test_a_long_list_of_set_aside_files_is_shortened(tmp_path, capsys):
    names = [f"s{i}-00004spp.exr" for i in range(5)]
    (tmp_path / "manifest.json").write_text(json.dumps(dict.fromkeys(names, "k")))
    assert remove_stale_files(tmp_path, set()) == names
    assert capsys.readouterr().out.endswith(
        ": s0-00004spp.exr, s1-00004spp.exr, s2-00004spp.exr, s3-00004spp.exr, ... (5 in all)\n"
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


def test_volumetric_files_the_dataset_does_not_have_are_set_aside_with_their_entries(tmp_path):
    entries = tmp_path / "manifest"
    entries.mkdir()
    for name in ("s-f0000-00004spp.exr", "s-f0001-00004spp.exr", "s-f0002-00004spp.exr"):
        (tmp_path / name).write_bytes(b"x")
        (entries / f"{name}.json").write_text(json.dumps({"key": f"k-{name}", "seconds": 1.5}))
    (tmp_path / "mine-f0000-00004spp.exr").write_bytes(b"x")  # no entry: a user's
    # another job's entry being written (src/io/atomic.py's temporary name): not a file of ours yet
    (entries / ".s-f0009-00004spp.exr.json.tmp-12-ab12cd34.json").write_text("{}")
    (entries / "gone-f0000-00004spp.exr.json").write_text("{}")  # an entry whose file is already gone
    removed = remove_stale_entries(
        tmp_path, "manifest", {"s-f0000-00004spp.exr", "s-f0001-00004spp.exr"}, now=5.0
    )
    assert removed == ["gone-f0000-00004spp.exr", "s-f0002-00004spp.exr"]
    assert _files(tmp_path) == [
        ".parked/entries/s-f0002-00004spp.exr.json",
        ".parked/s-f0002-00004spp.exr",
        "manifest/.s-f0009-00004spp.exr.json.tmp-12-ab12cd34.json",
        "manifest/s-f0000-00004spp.exr.json",
        "manifest/s-f0001-00004spp.exr.json",
        "mine-f0000-00004spp.exr",
        "s-f0000-00004spp.exr",
        "s-f0001-00004spp.exr",
    ]
    # back with its whole entry (the ladder's seconds, a sequence's seeds), and only with its key
    assert not restore_entry(tmp_path, "manifest", "s-f0002-00004spp.exr", "another key")
    assert restore_entry(tmp_path, "manifest", "s-f0002-00004spp.exr", "k-s-f0002-00004spp.exr")
    assert json.loads((entries / "s-f0002-00004spp.exr.json").read_text()) == {
        "key": "k-s-f0002-00004spp.exr",
        "seconds": 1.5,
    }
    assert (tmp_path / "s-f0002-00004spp.exr").is_file() and not list((tmp_path / ".parked").rglob("s-*"))


def test_jobs_setting_aside_the_same_stale_entry_at_once_all_succeed(tmp_path, monkeypatch, capsys):
    """Fanned-out volumetric render jobs start together and each sets aside the same stale files: a job
    may find an entry it listed already moved by another."""
    entries = tmp_path / "manifest"
    entries.mkdir()
    (entries / "old-f0000-00004spp.exr.json").write_text("{}")
    glob = Path.glob

    def glob_seeing_a_vanished_entry(self, pattern):
        return [*glob(self, pattern), self / "taken-f0000-00004spp.exr.json"]

    monkeypatch.setattr(Path, "glob", glob_seeing_a_vanished_entry)
    removed = remove_stale_entries(tmp_path, "manifest", set())
    assert removed == ["old-f0000-00004spp.exr", "taken-f0000-00004spp.exr"] and not any(entries.iterdir())
    assert f"{_set_aside(tmp_path, 2)}" in capsys.readouterr().out


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
    "dataset.ladder_spp=[1,2,4,8,16,32]",  # cpu's own reach up to 512, past this reference
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


# --- two tasks' configs in one data folder: the filter search's smoke data and the denoise task's ---------


def _render(data, overrides):
    from src.stages import render

    cfg = smoke_config(data, data / "run", overrides)
    return cfg, render(cfg)


def _mtimes(folder: Path) -> dict[str, int]:
    return {str(p.relative_to(folder)): p.stat().st_mtime_ns for p in folder.rglob("*.exr")}


@pytest.mark.slow
def test_the_filter_search_and_the_denoise_task_do_not_render_each_others_files_again(
    tmp_path, mitsuba_variant, capsys
):
    """~15 s. At `smoke` the filter search renders two scenes of each base (conf/task_dataset_profile/), the
    denoise task one, into the same folder; each used to delete the other's renders ("removed 9 earlier
    render(s)") and the next run rendered them again. Now each sets the other's aside and moves them back:
    after the first run of each, nothing is rendered again, every render keeps its file (mtime), and the
    raw folder holds, for the preprocessing and the fingerprint, what the running config makes."""
    search, first = _render(tmp_path, ["task=filter_search"])
    raw, ladder = Path(search.paths.raw), Path(search.paths.ladder)
    assert first["files_rendered"] == 6 * 3 and first["ladder"]["files_rendered"] > 0
    denoise, second = _render(tmp_path, [])
    assert denoise.paths.raw == search.paths.raw and denoise.paths.ladder == search.paths.ladder
    assert second["files_rendered"] == 0 and second["files_cached"] == 3 * 3  # the -0000 scenes are shared
    assert second["files_removed"] == 3 * 3  # the -0001 scenes, set aside
    searched = {**_mtimes(raw), **{f"ladder/{k}": v for k, v in _mtimes(ladder).items()}}
    # the raw data as the runs' tag and the prepared folder's cache key see them: each config's own
    fingerprints = {"denoise": data_fingerprint(raw)}
    capsys.readouterr()
    for overrides, scenes in ((["task=filter_search"], 6), ([], 3), (["task=filter_search"], 6)):
        _, again = _render(tmp_path, overrides)
        out = capsys.readouterr().out
        assert again["files_rendered"] == 0 and again["ladder"]["files_rendered"] == 0, out
        assert "earlier render(s)" not in out and "render: deleted" not in out  # nothing deleted
        assert sorted({p.name.rsplit("-", 1)[0] for p in raw.glob("*.exr")}) == sorted(
            f"{b}-{i:04d}" for b in ("cornell", "tabletop", "outdoor") for i in range(scenes // 3)
        )
        assert sorted(json.loads((raw / "manifest.json").read_text())) == sorted(
            p.name for p in raw.glob("*.exr")
        )
        task = "filter_search" if overrides else "denoise"
        assert fingerprints.setdefault(task, data_fingerprint(raw)) == data_fingerprint(raw)
    assert fingerprints["filter_search"] != fingerprints["denoise"]
    assert f"render: all 18 files up to date in {raw}, 9 of them moved back from .parked/\n" in out
    # every render the first two runs made is the same file (mtime): moved, never rendered again
    now = {**_mtimes(raw), **{f"ladder/{k}": v for k, v in _mtimes(ladder).items()}}
    assert {k.replace(".parked/", ""): v for k, v in now.items()} == {
        k.replace(".parked/", ""): v for k, v in searched.items()
    }
