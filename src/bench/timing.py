"""Wall-clock timing on a device: medians over repeated, synchronised calls; rounds of several functions
in a rotating order with their spread and per-round ratios; and the device's name."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import torch

from src.train.device import device_card


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


def round_order(n: int, round_index: int) -> list[int]:
    """The order in which round `round_index` runs `n` timed functions (indices 0..n-1).

    A Williams (1949) design: the first row 0, 1, n-1, 2, n-2, ... shifted by the round index (mod n);
    for odd n the rows of every second block of n rounds are mirrored. Over n rounds (2n for odd n) each
    function runs in every position equally often and directly after each other function equally often,
    so neither running first in a round (a cold cache, a clock ramping up) nor what ran just before (a
    predecessor that evicts the caches or heats the device) always favours the same function."""
    first, low, high = [0], 1, n - 1
    while len(first) < n:
        first.append(low)
        low += 1
        if len(first) < n:
            first.append(high)
            high -= 1
    row = [(i + round_index) % n for i in first]
    if n % 2 and (round_index // n) % 2:
        row.reverse()
    return row


@dataclass
class Rounds:
    """Seconds of each timed function per round (`seconds[name][r]`) and each round's order."""

    seconds: dict[str, list[float]]
    orders: list[list[str]]

    def csv_rows(self) -> list[dict[str, Any]]:
        """One row per function per round: {"round", "model", "seconds"}, rounds in order, each round's
        rows in the order the functions ran."""
        return [
            {"round": r, "model": name, "seconds": self.seconds[name][r]}
            for r, order in enumerate(self.orders)
            for name in order
        ]


def time_rounds(
    fns: Mapping[str, Callable[[], Any]],
    device: torch.device,
    rounds: int,
    warmup: int,
    clock: Callable[[], float] = time.perf_counter,
) -> Rounds:
    """Wall-clock seconds of each `fns[name]()` in `rounds` rounds after `warmup` untimed calls of each.

    A round calls every function once, in the order `round_order` gives it (it rotates between rounds),
    each call synchronised. A load change on a shared machine then hits all functions of a round alike,
    and the per-round ratios of two functions (`ratio_spread`) pair times measured under the same load."""
    names = list(fns)
    for name in names:
        for _ in range(warmup):
            fns[name]()
    _sync(device)
    seconds: dict[str, list[float]] = {name: [] for name in names}
    orders: list[list[str]] = []
    for r in range(rounds):
        order = [names[i] for i in round_order(len(names), r)]
        for name in order:
            start = clock()
            fns[name]()
            _sync(device)
            seconds[name].append(clock() - start)
        orders.append(order)
    return Rounds(seconds, orders)


@dataclass(frozen=True)
class Spread:
    """The median, quartiles (`statistics.quantiles`, method "inclusive": linear interpolation between
    the sorted samples, as numpy's default percentile) and range of some samples."""

    median: float
    q1: float
    q3: float
    low: float
    high: float

    @classmethod
    def of(cls, samples: Sequence[float]) -> Spread:
        values = list(samples)
        if len(values) < 2:
            return cls(*(values * 5))
        q1, median, q3 = statistics.quantiles(values, n=4, method="inclusive")
        return cls(median, q1, q3, min(values), max(values))


def ratio_spread(numerator: Sequence[float], denominator: Sequence[float]) -> tuple[Spread, list[float]]:
    """The per-round ratios numerator[r] / denominator[r] (same round, same load) and their spread."""
    ratios = [a / b for a, b in zip(numerator, denominator, strict=True)]
    return Spread.of(ratios), ratios


def device_name(device: torch.device) -> str:
    """The GPU's name, or the CPU's model and the thread count torch uses (`device_card`)."""
    card = device_card(device)
    if device.type == "cuda":
        return card["device_name"]
    return f"{card['device_name']}, {card['threads']} threads"
