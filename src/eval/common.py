"""Helpers shared by the evaluation stages of both tasks."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch


def sync(device: torch.device) -> None:
    """Wait for queued GPU work, so that wall-clock timings cover it (a no-op on the CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def mean_rows(rows: list[dict[str, Any]]) -> dict[str, float]:
    """Per float-valued column of per-image rows, its mean over the rows whose value is not NaN (a method
    whose output is undefined on an item scores NaN there, and the item's `undefined` column counts it);
    NaN when no row has a value."""
    keys = [k for k in rows[0] if isinstance(rows[0][k], float)]
    means = {}
    for k in keys:
        values = np.array([r[k] for r in rows], dtype=np.float64)
        values = values[~np.isnan(values)]
        means[k] = float(values.mean()) if values.size else float("nan")
    return means
