"""Is a prepared folder the one this config would make? A stage that reads `paths.prepared` without
preprocessing first (`stage=train`, `eval`, `select_features`, `search`) checks, when its job starts, that
the folder's recorded cache key equals the key `stage=preprocess` would give it now. Otherwise it would
train or score on data made with other `task.preprocess` or `dataset.preprocess` settings (a `stage=preprocess
task.preprocess.patch_size=16` before a plain `stage=train`) or from other raw data, while its run
records this config. Why at job start: before any run is opened or file written (the docs' rule for bad
input)."""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable
from pathlib import Path

from src.errors import ConfigError

#: The stages that read the prepared folder.
READERS = frozenset({"train", "eval", "select_features", "search"})


def reads_prepared_only(stages: Iterable[str]) -> bool:
    """Whether a job with these stages reads the prepared folder without preprocessing first."""
    stages = set(stages)
    return "preprocess" not in stages and bool(READERS & stages)


def check_prepared_is_current(
    record_file: Path, key_of: Callable[[Path], str], current_raw: Path | None = None
) -> None:
    """A one-line ConfigError unless the cache key in `record_file` (the prepared folder's provenance)
    equals `key_of(raw)`, the current config's key for the raw data the folder was made from (`paths.raw`
    as that preprocess run had it, so a user's KPCN folder need not be named again), or else
    `key_of(current_raw)` (this config's `paths.raw`: a data folder made under another working directory
    or moved, e.g. by `dvc repro` with a relative `paths.data`, records a raw path that no longer points
    at its raw data, while `stage=preprocess` finds the folder up to date). For a job whose stages
    `reads_prepared_only`; nothing to check when there is no record (the stage's `inputs` then names the
    stage that makes it)."""
    try:
        record = json.loads(record_file.read_text())
        raw = Path(record["config"]["paths"]["raw"])
    except (OSError, ValueError, KeyError, TypeError):
        return
    wanted = record.get("cache_key")
    if wanted == key_of(raw):
        return
    if current_raw is not None and Path(current_raw) != raw and wanted == key_of(Path(current_raw)):
        return
    raise ConfigError(
        f"{record_file.parent}: made by stage=preprocess with other task.preprocess or dataset.preprocess "
        f"settings or from other raw data ({raw}) than this config's; run stage=preprocess (or dvc repro) "
        "first"
    )
