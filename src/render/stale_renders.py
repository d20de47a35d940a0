"""Removing renders the current configuration no longer makes, so that a data folder holds exactly what
its config renders.

Why: the render stages keep every file whose render key is unchanged and re-render the others, but a
file only an earlier config produced (another sample count, a scene dropped from the list) would stay,
and the stages that read the whole folder (`preprocess`, which groups every `*.exr` of `paths.raw`)
would mix two configurations, e.g. fail on references of another size. Each profile has its own data
folder (`paths.dataset` in conf/config.yaml); these functions keep an override within a profile
(`dataset.noisy_spp=[4,8]`, fewer scenes) from colliding either.

Only what the harness rendered is ever removed: a file counts as ours when its render manifest names it
(`manifest.json` of the still images, `manifest/<file>.json` of the volumetric sequences,
`nrbench_render.json` inside a multi-view scene folder). A user's own files in the same folder (real
KPCN EXRs under `paths.raw`, their own Blender scenes) have no manifest entry and are never touched.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Collection
from pathlib import Path

from src.io.atomic import atomic_write_json


def _report(removed: list[str], where: Path) -> list[str]:
    if removed:
        shown = ", ".join(removed[:4]) + (f", ... ({len(removed)} in all)" if len(removed) > 4 else "")
        print(
            f"render: removed {len(removed)} earlier render(s) the config no longer makes from {where}: "
            f"{shown}"
        )
    return removed


def remove_stale_files(raw_dir: Path, expected: Collection[str]) -> list[str]:
    """Still images: delete every file `raw_dir/manifest.json` lists that is not in `expected` (the file
    names of the current config), and its manifest entry; returns the names removed, sorted. Files the
    manifest does not list are left alone."""
    manifest_path = raw_dir / "manifest.json"
    if not manifest_path.is_file():
        return []
    manifest = json.loads(manifest_path.read_text())
    stale = sorted(name for name in manifest if name not in expected)
    for name in stale:
        (raw_dir / name).unlink(missing_ok=True)
        del manifest[name]
    if stale:
        atomic_write_json(manifest_path, manifest)
    return _report(stale, raw_dir)


def remove_stale_entries(raw_dir: Path, manifest_dir: str, expected: Collection[str]) -> list[str]:
    """Volumetric sequences: for every entry `raw_dir/<manifest_dir>/<file>.json` whose file is not in
        `expected` (all files of the whole dataset, not only a fanned-out job's subset: the other subsets'
        files stay), delete the file, then its entry (so an interruption leaves an entry without its file,
        which is rendered again, never a file without its entry); hidden names are another job's temporaries
    (`src.io.atomic`) and are skipped. Returns the names removed, sorted."""
    entries = raw_dir / manifest_dir
    if not entries.is_dir():
        return []
    names = (p.name.removesuffix(".json") for p in entries.glob("*.json") if not p.name.startswith("."))
    stale = sorted(name for name in names if name not in expected)
    for name in stale:
        (raw_dir / name).unlink(missing_ok=True)
        (entries / f"{name}.json").unlink(missing_ok=True)
    return _report(stale, raw_dir)


def remove_stale_scenes(out_dir: Path, key_file: str, expected: Collection[str]) -> list[str]:
    """Multi-view scenes: delete every scene folder of `out_dir` that holds our `key_file` and is not in
    `expected` (the config's `dataset.scenes`); hidden folders (a scene being written, `src.io.atomic`)
    are skipped. Returns the names removed, sorted."""
    if not out_dir.is_dir():
        return []
    ours = (
        p for p in out_dir.iterdir() if p.is_dir() and not p.name.startswith(".") and (p / key_file).is_file()
    )
    stale = sorted(p.name for p in ours if p.name not in expected)
    for name in stale:
        shutil.rmtree(out_dir / name)
    return _report(stale, out_dir)
