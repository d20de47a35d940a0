"""Wall-clock timing on a device: medians over repeated, synchronised calls, and the device's name."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import torch


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_calls(
    fns: Sequence[Callable[[], Any]], device: torch.device, repeats: int, warmup: int
) -> list[float]:
    """Median wall-clock seconds of each `fn()` over `repeats` runs after `warmup` untimed ones.

    The functions are timed round-robin (a, b, a, b, ...), so a load change on a shared machine affects
    all of them alike and their ratio (e.g. KPCN / its network alone) stays meaningful."""
    for fn in fns:
        for _ in range(warmup):
            fn()
    _sync(device)
    times: list[list[float]] = [[] for _ in fns]
    for _ in range(repeats):
        for fn, samples in zip(fns, times, strict=True):
            start = time.perf_counter()
            fn()
            _sync(device)
            samples.append(time.perf_counter() - start)
    return [statistics.median(samples) for samples in times]


def time_runs(fn: Callable[[], Any], device: torch.device, runs: int, warmup: int = 1) -> float:
    """Median wall-clock seconds of `runs` calls of `fn()` after `warmup` untimed ones, each call
    synchronised (a median, so a load spike on a shared machine does not decide the result)."""
    return time_calls([fn], device, runs, warmup)[0]


def device_name(device: torch.device) -> str:
    """The GPU's name, or the CPU thread count torch uses."""
    if device.type == "cuda":
        return torch.cuda.get_device_name(device)
    return f"{torch.get_num_threads()} threads"
