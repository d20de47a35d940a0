"""Learning curves as a local CSV beside the checkpoints (one row per logged evaluation point).

MLflow holds the same values; the file exists so that DVC can declare it as a `plots` output
(`dvc plots show` / `dvc plots diff`) without reading the tracking store. It is rewritten whole,
atomically, from the rows kept in the checkpoint, so a resumed run continues the same file.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from src.io.atomic import atomic_write_csv


def write_curves(path: str | Path, rows: Sequence[Mapping[str, float]]) -> Path:
    """Write `rows` (dicts with a `step` key; columns are the union of keys, `step` first) as CSV."""
    columns = ["step", *sorted({k for row in rows for k in row} - {"step"})]
    return atomic_write_csv(path, rows, columns)
