"""Which volumetric features a run reads when `dataset.feature_selection.size` = k: the start set plus the
first k of a finished selection (`<dir>/selection.json`, written by `stage=select_features`) or k
candidates drawn at random (the study's baseline arm). Plain lists and one JSON file: the data kind
settles a run's features from it when a job starts, and the selection stage
(src/train/select_features.py) writes what it reads."""

from __future__ import annotations

import json
import random
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from src.data.volume_features import VOLUME_CANDIDATE_FEATURES
from src.errors import ConfigError

#: Where the settings live, for error messages.
FEATURE_SELECTION_KEY = "dataset.feature_selection"
SIZE_KEY = f"{FEATURE_SELECTION_KEY}.size"
#: The selection stage's ordered result, in `dataset.feature_selection.dir`.
SELECTION_FILE = "selection.json"


def remaining_candidates(candidates: Sequence[str], start: Sequence[str]) -> list[str]:
    """`candidates` without the start set and repeats, in order."""
    return [c for c in dict.fromkeys(candidates) if c not in set(start)]


def selection_candidates(start: list[str], candidates: list[str] | None) -> list[str]:
    """The features tried: `candidates`, or every stored candidate not in the start set."""
    return remaining_candidates(candidates if candidates is not None else VOLUME_CANDIDATE_FEATURES, start)


def check_size(size: int, available: int) -> None:
    """A one-line ConfigError naming `dataset.feature_selection.size` unless 0 <= size <= available."""
    if isinstance(size, bool) or not isinstance(size, int) or not 0 <= size <= available:
        raise ConfigError(f"{SIZE_KEY}={size!r}: expected an integer in [0, {available}] (features to add)")


def selected_features(rows: Sequence[dict], size: int) -> list[str]:
    """The start set plus the first `size` features the greedy selection added (its rows: round, added,
    features, loss); a one-line ConfigError when `size` < 0 or more than the rounds run."""
    check_size(size, len(rows) - 1)
    return list(rows[size]["features"])


def random_features(candidates: Sequence[str], start: Sequence[str], size: int, seed: int) -> list[str]:
    """The start set plus `size` candidates (not in `start`) chosen at random: the baseline arm of the
    study. The sets are nested over `size` for one seed (a prefix of one shuffle), as the greedy ones are;
    a one-line ConfigError when `size` is out of range."""
    remaining = remaining_candidates(candidates, start)
    check_size(size, len(remaining))
    random.Random(seed).shuffle(remaining)
    return [*start, *remaining[:size]]


def features_for_size(selection: Any) -> list[str]:
    """What `dataset.volume_features` becomes with `size` = k (`selection` is `dataset.feature_selection`):
    the start set plus the selection's first k (`order: greedy`, read from `<dir>/selection.json`) or k
    candidates drawn at random (`order: random`)."""
    start, size = [str(f) for f in selection.start], int(selection.size)
    if selection.order == "random":
        pool = selection_candidates(start, selection.candidates)
        return random_features(pool, start, size, int(selection.random_seed))
    path = Path(selection.dir) / SELECTION_FILE
    if not path.is_file():
        raise ConfigError(
            f"{FEATURE_SELECTION_KEY}.size={size}: {path} not found; run stage=select_features "
            f"dataset=volumetric first (or set {FEATURE_SELECTION_KEY}.order=random)"
        )
    rows = json.loads(path.read_text())["rows"]
    if [str(f) for f in rows[0]["features"]] != start:
        found = rows[0]["features"]
        raise ConfigError(f"{FEATURE_SELECTION_KEY}.start={start}: {path} was selected from {found}")
    return selected_features(rows, size)
