"""Multi-buffer EXR files checked against a declared layout: the one mechanism every kind of rendered
data goes through (the KPCN convention in `kpcn_buffers.py` is one layout; later data declares its own).

Loading validates what later stages silently assume (all channels present, one size, float pixels,
finite, non-negative radiance and variance), because a NaN or a wrong channel name otherwise surfaces
hours later as a diverged training run. Bad values can be repaired instead of failing, by an explicit,
counted and logged `RepairPolicy`. Files named differently can be mapped with `aliases` instead of
guessing alternative names.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Literal

import numpy as np

from src.errors import ConfigError, DataError
from src.io.exr import format_names, read_exr, write_exr

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BufferLayout:
    """The declared channels of one kind of multi-buffer EXR: what the loader checks a file against.

    buffers: buffer name -> its EXR channel names, in the order of the (H, W, C) array's last axis;
    radiance: buffers holding radiance (never negative; `RepairPolicy.firefly_clamp` applies);
    variance: buffers holding variances (never negative);
    optional: buffers a file may lack (features added to the layout after data in it already existed, e.g.
        KPCN's `position` and `secondary_albedo`): loading all buffers skips an optional one whose channels
        are all absent (one channel of it present but another missing is still an error), and asking for
        it by name (`buffers=`) in a file without it is the usual missing-channel error.
    A new kind of data (e.g. volumetric sequences) declares its own layout and gets every check.
    """

    name: str
    buffers: Mapping[str, tuple[str, ...]]
    radiance: tuple[str, ...] = ()
    variance: tuple[str, ...] = ()
    optional: tuple[str, ...] = ()

    @cached_property  # read once per channel of every file loaded: built once per layout
    def channel_buffer(self) -> dict[str, str]:
        """EXR channel name -> the buffer it belongs to."""
        return {ch: b for b, chans in self.buffers.items() for ch in chans}

    def load(
        self,
        path: str | os.PathLike[str],
        repair: RepairPolicy | None = None,
        expected_size: tuple[int, int] | None = None,
        aliases: Mapping[str, str] | None = None,
        buffers: Iterable[str] | None = None,
    ) -> tuple[dict[str, np.ndarray], RepairReport]:
        """Load and validate one EXR of this layout (`load_buffers`; see it for the checks)."""
        return load_buffers(path, self, repair, expected_size, aliases, buffers)

    def write(
        self, path: str | os.PathLike[str], buffers: Mapping[str, np.ndarray], compression: str = "zip"
    ) -> Path:
        """Write buffers of this layout as one float32 EXR in its channel naming (atomically)."""
        return write_buffers(path, self, buffers, compression=compression)


#: Where a RepairPolicy comes from in the config (its errors name these keys).
REPAIR_KEY = "task.preprocess.repair"


@dataclass(frozen=True)
class RepairPolicy:
    """What to do with bad values instead of failing; everything off (= fail) by default.

    nonfinite: "zero" replaces NaN/Inf in any channel by 0.
    negative: "clamp" sets negative radiance (color/diffuse/specular) and negative variance to 0.
    firefly_clamp: caps color/diffuse/specular at this value. Each buffer is clamped on its own and nothing
        is recomputed, so in clamped pixels color may differ from diffuse + specular (and the variances
        still describe the unclamped samples).
    """

    nonfinite: Literal["error", "zero"] = "error"
    negative: Literal["error", "clamp"] = "error"
    firefly_clamp: float | None = None

    def __post_init__(self) -> None:
        if self.nonfinite not in ("error", "zero"):
            raise ConfigError(f"{REPAIR_KEY}.nonfinite={self.nonfinite!r}; expected 'error' or 'zero'")
        if self.negative not in ("error", "clamp"):
            raise ConfigError(f"{REPAIR_KEY}.negative={self.negative!r}; expected 'error' or 'clamp'")
        if self.firefly_clamp is not None and not (
            np.isfinite(self.firefly_clamp) and self.firefly_clamp > 0
        ):
            raise ConfigError(
                f"{REPAIR_KEY}.firefly_clamp={self.firefly_clamp!r}; expected null or a positive number"
            )


@dataclass
class RepairReport:
    """Repairs applied to one file: counts[kind][channel] = number of values changed.

    kind is "nonfinite" (set to 0), "negative" (clamped to 0) or "firefly" (clamped to firefly_clamp).
    """

    path: str
    counts: dict[str, dict[str, int]] = field(default_factory=dict)

    def add(self, kind: str, channel: str, count: int) -> None:
        if count:
            self.counts.setdefault(kind, {})[channel] = count

    @property
    def total(self) -> int:
        return sum(n for per_channel in self.counts.values() for n in per_channel.values())

    def summary(self) -> str:
        """One line, e.g. `nonfinite: R=3, diffuse.G=1; firefly: R=12` or `no repairs`."""
        if not self.total:
            return "no repairs"
        return "; ".join(
            f"{kind}: " + ", ".join(f"{ch}={n}" for ch, n in per_channel.items())
            for kind, per_channel in self.counts.items()
        )


def buffers_to_channels(layout: BufferLayout, buffers: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """(H, W, C) buffers (any subset of the layout's; (H, W) allowed when C = 1) -> flat float32 channels."""
    out = {}
    for name, arr in buffers.items():
        if name not in layout.buffers:
            raise DataError(f"unknown {layout.name} buffer {name!r}; known: {format_names(layout.buffers)}")
        chans = layout.buffers[name]
        arr = np.asarray(arr)
        if arr.ndim == 2 and len(chans) == 1:
            arr = arr[..., None]
        if arr.ndim != 3 or arr.shape[-1] != len(chans):
            raise DataError(
                f"{layout.name} buffer {name!r} has shape {arr.shape}; expected (H, W, {len(chans)})"
            )
        for i, ch in enumerate(chans):
            out[ch] = np.ascontiguousarray(arr[..., i], dtype=np.float32)
    return out


def write_buffers(
    path: str | os.PathLike[str],
    layout: BufferLayout,
    buffers: Mapping[str, np.ndarray],
    compression: str = "zip",
) -> Path:
    """Write `layout` buffers as one float32 EXR in its channel naming (atomically)."""
    return write_exr(path, buffers_to_channels(layout, buffers), compression=compression)


def _label(layout: BufferLayout, ch: str, file_ch: str) -> str:
    alias = f"alias of {ch!r}, " if file_ch != ch else ""
    return f"{file_ch!r} ({alias}buffer {layout.channel_buffer[ch]!r})"


def _repair_channel(
    layout: BufferLayout,
    path: Path,
    ch: str,
    file_ch: str,
    arr: np.ndarray,
    policy: RepairPolicy,
    report: RepairReport,
) -> np.ndarray:
    """Check one float32 channel against the buffer's value range; repair in place if the policy says so."""
    buf = layout.channel_buffer[ch]
    bad = ~np.isfinite(arr)
    if bad.any():
        if policy.nonfinite != "zero":
            n_nan = int(np.isnan(arr).sum())
            raise DataError(
                f"{path}: channel {_label(layout, ch, file_ch)} has {int(bad.sum())} non-finite values "
                f"({n_nan} NaN, {int(bad.sum()) - n_nan} Inf); repair with {REPAIR_KEY}.nonfinite=zero"
            )
        arr[bad] = 0.0
        report.add("nonfinite", file_ch, int(bad.sum()))
    if buf in layout.radiance or buf in layout.variance:
        neg = arr < 0
        if neg.any():
            if policy.negative != "clamp":
                what = "variance" if buf in layout.variance else "radiance"
                label = _label(layout, ch, file_ch)
                raise DataError(
                    f"{path}: channel {label} has {int(neg.sum())} negative {what} values "
                    f"(min {arr.min():g}); repair with {REPAIR_KEY}.negative=clamp"
                )
            arr[neg] = 0.0
            report.add("negative", file_ch, int(neg.sum()))
    if buf in layout.radiance and policy.firefly_clamp is not None:
        hot = arr > policy.firefly_clamp
        arr[hot] = policy.firefly_clamp
        report.add("firefly", file_ch, int(hot.sum()))
    return arr


def load_buffers(
    path: str | os.PathLike[str],
    layout: BufferLayout,
    repair: RepairPolicy | None = None,
    expected_size: tuple[int, int] | None = None,
    aliases: Mapping[str, str] | None = None,
    buffers: Iterable[str] | None = None,
) -> tuple[dict[str, np.ndarray], RepairReport]:
    """Load and validate an EXR of `layout` -> ({buffer: float32 (H, W, C)}, repairs applied).

    buffers: which buffers to load (default: all of the layout's, in that order, but the layout's
        `optional` buffers only when the file has any of their channels).
    aliases: our channel name -> the name in this file, for data named differently, e.g.
        `{"normal.R": "normal.X", "normal.G": "normal.Y", "normal.B": "normal.Z"}`. Only exactly the
        listed names are accepted; no alternative spellings are guessed.
    Raises a one-line DataError for a missing channel, a size different from `expected_size` (H, W) or
    between channels, a non-float channel, NaN/Inf, or negative radiance/variance, unless `repair`
    allows fixing the value errors; repairs are counted in the report and logged once per file.
    """
    path = Path(path)
    policy = repair or RepairPolicy()
    aliases = dict(aliases or {})
    names = _buffer_names(layout, aliases, buffers)
    data = read_exr(path)
    if buffers is None:  # all buffers: the optional ones only where the file has them
        names = [
            b
            for b in names
            if b not in layout.optional or any(aliases.get(ch, ch) in data for ch in layout.buffers[b])
        ]
    wanted = [(ch, aliases.get(ch, ch)) for b in names for ch in layout.buffers[b]]
    _check_channels(layout, path, data, wanted, expected_size)

    report = RepairReport(str(path))
    out = {}
    for b in names:
        chans = [
            _repair_channel(
                layout,
                path,
                ch,
                aliases.get(ch, ch),
                data[aliases.get(ch, ch)].astype(np.float32),
                policy,
                report,
            )
            for ch in layout.buffers[b]
        ]
        out[b] = np.stack(chans, axis=-1)
    if report.total:
        log.warning("%s: repaired %d values (%s)", path, report.total, report.summary())
    return out, report


def _buffer_names(
    layout: BufferLayout, aliases: Mapping[str, str], buffers: Iterable[str] | None
) -> list[str]:
    """The buffers to load (all of the layout's by default, duplicates dropped), after checking that the
    aliases and the buffers name known channels and buffers (one-line ConfigError otherwise)."""
    unknown = [a for a in aliases if a not in layout.channel_buffer]
    if unknown:
        raise ConfigError(f"aliases for unknown {layout.name} channels {format_names(map(repr, unknown))}")
    names = list(layout.buffers) if buffers is None else list(dict.fromkeys(buffers))
    unknown = [b for b in names if b not in layout.buffers]
    if unknown:
        known = format_names(layout.buffers)
        raise ConfigError(f"unknown {layout.name} buffers {format_names(map(repr, unknown))}; known: {known}")
    return names


def _check_channels(
    layout: BufferLayout,
    path: Path,
    data: Mapping[str, np.ndarray],
    wanted: list[tuple[str, str]],
    expected_size,
) -> None:
    """One-line DataError unless every wanted (our name, file name) channel is in the file, float, and of
    `expected_size` (H, W), or else of the first channel's size."""
    missing = [_label(layout, ch, file_ch) for ch, file_ch in wanted if file_ch not in data]
    if missing:
        noun = "channel" if len(missing) == 1 else "channels"
        raise DataError(f"{path}: missing EXR {noun} {format_names(missing, 8)}; found: {format_names(data)}")

    first_ch = wanted[0][1]
    size = expected_size or data[first_ch].shape
    for _, file_ch in wanted:
        shape = data[file_ch].shape
        if tuple(shape) != tuple(size):
            ref = "expected" if expected_size else f"channel {first_ch!r} is"
            raise DataError(
                f"{path}: channel {file_ch!r} is {shape[0]}x{shape[1]} (HxW), {ref} {size[0]}x{size[1]}"
            )
        if data[file_ch].dtype.kind != "f":
            raise DataError(
                f"{path}: channel {file_ch!r} has pixel type {data[file_ch].dtype}; expected float"
            )
