"""Learning curves as a local CSV beside the checkpoints (one row per logged evaluation point).

MLflow holds the same values; the file exists so that DVC can declare it as a `plots` output
(`dvc plots show` / `dvc plots diff`) without reading the tracking store. It is rewritten whole,
atomically, from the rows kept in the checkpoint, so a resumed run continues the same file.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Mapping, Sequence
from pathlib import Path

from src.io.atomic import atomic_write_text


def write_curves(path: str | Path, rows: Sequence[Mapping[str, float]]) -> Path:
    """Write `rows` (dicts with a `step` key; columns are the union of keys, `step` first) as CSV."""
    columns = ["step", *sorted({k for row in rows for k in row} - {"step"})]
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=columns, lineterminator="\n")
    writer.writeheader()
    writer.writerows(rows)
    return atomic_write_text(path, buffer.getvalue())
