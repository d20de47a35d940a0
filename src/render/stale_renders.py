"""Setting aside the renders the current configuration does not make, so that a data folder holds exactly
what its config renders, without deleting what another config at the same profile still uses.

Why not keep them in place: the render stages keep every file whose render key is unchanged and re-render
the others, but the stages that read the whole folder (`preprocess`, which groups every `*.exr` of
`paths.raw`) would mix two configurations, e.g. fail on references of another size or train on another
task's scenes. Each profile has its own data folder (`paths.dataset` in conf/config.yaml), yet two
configurations can share one: the filter search's smoke data (two scenes per base,
conf/task_dataset_profile/) and the denoise task's (one), or an override (`dataset.noisy_spp=[4,8]`).

Why not delete them: each of two such configs would delete the other's renders and the next run of the
other would render them again. So a render the config does not make is moved into the folder's
`.parked/` (`PARKED_DIR`; a rename, instant), with its render key and the time it was set aside; a render
stage that needs a file whose parked copy has the render key it wants moves it back instead of rendering
it (`restore_file`, `restore_entry`). A parked render nobody moves back for `PARK_DAYS` days is deleted at
the next render in that folder: so a render no config makes any longer is cleaned, after that time
(deleting `.parked/` by hand at any time is safe: what is needed again is rendered again). The data
fingerprint (`src.provenance.data_fingerprint`) and the readers never look inside `.parked/`, and
.dvcignore leaves it out of DVC's outs.

Only what the harness rendered is ever moved: a file counts as ours when its render manifest names it
(`manifest.json` of the still images, `manifest/<file>.json` of the volumetric sequences and of the
ladders, `nrbench_render.json` inside a multi-view scene folder). A user's own files in the same folder
(real KPCN EXRs under `paths.raw`, their own Blender scenes) have no manifest entry and are never touched.
Multi-view scene folders (one task, `task=nerf`) are still deleted, not parked (`remove_stale_scenes`).
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Collection
from pathlib import Path

from src.io.atomic import atomic_write_json
from src.provenance import PARKED_DIR

#: Days a parked render is kept without being moved back (module docstring).
PARK_DAYS = 30
#: Inside `PARKED_DIR`: one `<file>.json` per parked file: its render key, when it was parked, and its
#: manifest entry (the volumetric and ladder entries hold more than the key).
_PARK_ENTRIES = "entries"


def _shown(names: list[str]) -> str:
    return ", ".join(names[:4]) + (f", ... ({len(names)} in all)" if len(names) > 4 else "")


def _report(removed: list[str], where: Path) -> list[str]:
    if removed:
        print(
            f"render: removed {len(removed)} earlier render(s) the config no longer makes from {where}: "
            f"{_shown(removed)}"
        )
    return removed


def _report_parked(parked: list[str], where: Path) -> list[str]:
    if parked:
        print(
            f"render: set aside {len(parked)} render(s) this config does not make, for another config "
            f"that may (moved back when one needs them, deleted after {PARK_DAYS} days unused) from "
            f"{where} into {where / PARKED_DIR}: {_shown(parked)}"
        )
    return parked


def _park_entry_path(folder: Path, name: str) -> Path:
    return folder / PARKED_DIR / _PARK_ENTRIES / f"{name}.json"


def _park(folder: Path, name: str, key: str | None, entry: dict | None, now: float | None) -> None:
    """Move `folder/name` into `folder/.parked/`, then write its park entry (key, time, manifest entry).
    A file already gone (deleted by hand, or parked by another job meanwhile) is not parked."""
    parked = folder / PARKED_DIR / name
    parked.parent.mkdir(parents=True, exist_ok=True)
    try:
        os.replace(folder / name, parked)
    except FileNotFoundError:
        return
    record = {"key": key, "parked_at": time.time() if now is None else now, "entry": entry}
    atomic_write_json(_park_entry_path(folder, name), record)


def _parked_record(folder: Path, name: str, key: str) -> dict | None:
    """The park entry of `name` when its parked file exists and has render key `key`, else None."""
    try:
        record = json.loads(_park_entry_path(folder, name).read_text())
    except (OSError, ValueError):
        return None
    if record.get("key") != key or not (folder / PARKED_DIR / name).is_file():
        return None
    return record


def _unpark(folder: Path, name: str) -> bool:
    """Move the parked `name` back into `folder` (False when another job took it first)."""
    try:
        os.replace(folder / PARKED_DIR / name, folder / name)
    except FileNotFoundError:
        return False
    return True


def restore_file(raw_dir: Path, name: str, key: str, manifest: dict) -> bool:
    """Still images: move the parked `name` back into `raw_dir` when its render key is `key`, and record
    it in `manifest` (saved); True when it was, so the caller need not render it."""
    if _parked_record(raw_dir, name, key) is None or not _unpark(raw_dir, name):
        return False
    manifest[name] = key
    atomic_write_json(raw_dir / "manifest.json", manifest)
    _park_entry_path(raw_dir, name).unlink(missing_ok=True)
    return True


def restore_entry(folder: Path, manifest_dir: str, name: str, key: str) -> bool:
    """Volumetric sequences and ladders: move the parked `name` back into `folder` when its render key is
    `key`, with its manifest entry `folder/<manifest_dir>/<name>.json` as it was; True when it was."""
    record = _parked_record(folder, name, key)
    if record is None or not _unpark(folder, name):
        return False
    atomic_write_json(folder / manifest_dir / f"{name}.json", record.get("entry") or {"key": key})
    _park_entry_path(folder, name).unlink(missing_ok=True)
    return True


def expire_parked(folder: Path, now: float | None = None) -> list[str]:
    """Delete the renders parked in `folder/.parked/` more than `PARK_DAYS` days before `now`, and parked
    files without a park entry (a park interrupted between the move and the entry); returns their names,
    sorted. Hidden names (another job's temporaries, `src.io.atomic`) are skipped."""
    park = folder / PARKED_DIR
    if not park.is_dir():
        return []
    now = time.time() if now is None else now
    expired = []
    entries = park / _PARK_ENTRIES
    for path in sorted(entries.glob("*.json")) if entries.is_dir() else []:
        if path.name.startswith("."):
            continue
        try:
            parked_at = float(json.loads(path.read_text())["parked_at"])
        except (OSError, ValueError, KeyError, TypeError):
            parked_at = 0.0  # unreadable: as old as can be
        if now - parked_at > PARK_DAYS * 86400:
            name = path.name.removesuffix(".json")
            (park / name).unlink(missing_ok=True)
            path.unlink(missing_ok=True)
            expired.append(name)
    for path in park.iterdir():
        if path.is_file() and not path.name.startswith(".") and not (entries / f"{path.name}.json").exists():
            path.unlink(missing_ok=True)
            expired.append(path.name)
    expired.sort()
    if expired:
        print(
            f"render: deleted {len(expired)} render(s) set aside more than {PARK_DAYS} days ago and not "
            f"needed since from {park}: {_shown(expired)}"
        )
    return expired


def remove_stale_files(raw_dir: Path, expected: Collection[str], now: float | None = None) -> list[str]:
    """Still images: set aside every file `raw_dir/manifest.json` lists that is not in `expected` (the file
    names of the current config) into `raw_dir/.parked/`, and drop its manifest entry (an entry whose file
    is already gone is dropped too); returns those names, sorted. Files the manifest does not list are
    left alone. Parked renders past `PARK_DAYS` are deleted first (`expire_parked`)."""
    expire_parked(raw_dir, now)
    manifest_path = raw_dir / "manifest.json"
    if not manifest_path.is_file():
        return []
    manifest = json.loads(manifest_path.read_text())
    stale = sorted(name for name in manifest if name not in expected)
    for name in stale:
        _park(raw_dir, name, manifest[name], None, now)
        del manifest[name]
    if stale:
        atomic_write_json(manifest_path, manifest)
    return _report_parked(stale, raw_dir)


def remove_stale_entries(
    raw_dir: Path, manifest_dir: str, expected: Collection[str], now: float | None = None
) -> list[str]:
    """Volumetric sequences and ladders: for every entry `raw_dir/<manifest_dir>/<file>.json` whose file is
    not in `expected` (all files of the whole dataset, not only a fanned-out job's subset: the other
    subsets' files stay), set the file aside into `raw_dir/.parked/` with its entry, then delete the entry
    (so an interruption leaves an entry without its file, which is rendered again, never a file without its
    entry); hidden names are another job's temporaries (`src.io.atomic`) and are skipped. Returns the names
    set aside, sorted. Parked renders past `PARK_DAYS` are deleted first (`expire_parked`)."""
    expire_parked(raw_dir, now)
    entries = raw_dir / manifest_dir
    if not entries.is_dir():
        return []
    names = (p.name.removesuffix(".json") for p in entries.glob("*.json") if not p.name.startswith("."))
    stale = sorted(name for name in names if name not in expected)
    for name in stale:
        entry_path = entries / f"{name}.json"
        try:
            entry = json.loads(entry_path.read_text())
        except (OSError, ValueError):  # removed meanwhile by another job setting the same file aside
            entry = None
        if isinstance(entry, dict):
            _park(raw_dir, name, entry.get("key"), entry, now)
        entry_path.unlink(missing_ok=True)
    return _report_parked(stale, raw_dir)


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
