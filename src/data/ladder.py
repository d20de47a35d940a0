"""The sample-count ladder of the held-out images: plain renders of each held-out scene (every frame of a
sequence) at the counts `dataset.ladder_spp`, which the evaluation reads to say how many samples per pixel
a plain render needs to reach a denoised image's error (`src.metrics.spp_equivalent`).

Layout, in `paths.ladder` (beside the raw folder, not in it: the raw data's fingerprint, and with it
the prepared folders' cache keys, stays what it was): ``<file>`` holds one render's linear colour
(channels R, G, B, float32; the still images' ``<scene>-<NNNNN>spp.exr``, the sequences'
``<scene>-f<FFFF>-<NNNNN>spp.exr``) and ``manifest/<file>.json`` its render key, sample count and
render seconds (the clock covers the render passes only: not the scene's build, not the file's
writing; null for a rung averaged from a Noisebase set's stored samples, which has no render time here).
The render stage writes them (`src.render.ladder_render`); this module names and reads them.

Each rung is its own render (pass seeds of the role ``ladder``), independent of the noisy inputs and of
the reference, so a noisy input scored against the ladder is an honest check: its equivalent should come
out near its own count. A Noisebase set's rungs are averaged from its stored samples instead
(`src.data.noisebase.ladder_color`): the last k, where the inputs take the first n.
"""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from src.data.splits import exr_name
from src.data.volume_buffers import volume_exr_name
from src.errors import ConfigError, DataError
from src.io.exr import read_exr

MANIFEST_DIR = "manifest"
#: The role of a ladder render (its pass seeds and render key).
LADDER_ROLE = "ladder"


def ladder_counts(ds: Mapping) -> list[int]:
    """The sorted distinct counts of `dataset.ladder_spp` (empty when null or []); a ConfigError unless every
    count is >= 1 and below `reference_spp` (a rung at the reference's count or above measures nothing the
    reference's own noise lets one read: `src.metrics.spp_equivalent.measurable_limit`)."""
    counts = sorted({int(s) for s in ds.get("ladder_spp") or []})
    reference = int(ds["reference_spp"])
    bad = [s for s in counts if not 1 <= s < reference]
    if bad:
        raise ConfigError(
            f"dataset.ladder_spp: {bad} outside 1..{reference - 1}; expected sample counts >= 1 and below "
            f"dataset.reference_spp={reference}"
        )
    if len(counts) == 1:
        raise ConfigError(f"dataset.ladder_spp={counts}: expected at least two counts (a fit of a / n + c)")
    return counts


def ladder_file(scene: str, spp: int, frame: int | None = None) -> str:
    """The ladder file of one rung, relative to the ladder folder (a still image's when `frame` is None)."""
    return exr_name(scene, spp) if frame is None else volume_exr_name(scene, frame, spp)


def entry_path(ladder_dir: Path, file: str) -> Path:
    """The manifest entry of `file`: ``<ladder_dir>/manifest/<file>.json``."""
    return ladder_dir / MANIFEST_DIR / f"{file}.json"


@dataclass(frozen=True)
class Ladder:
    """One held-out scene's rungs: per count the (F, H, W, 3) colour of every frame (F = 1 for a still) and
    the mean render seconds of a frame (NaN for a ladder that was not rendered here)."""

    scene: str
    frames: dict[int, np.ndarray]
    seconds: dict[int, float]


def read_ladder(ladder_dir: Path, scene: str, counts: Sequence[int], frames: int | None) -> Ladder:
    """The rungs `counts` of `scene` (`frames` frames of a sequence, None: a still image) from
    ``ladder_dir`` (`paths.ladder`); a DataError naming the first missing file and what makes it."""
    ladder_dir = Path(ladder_dir)
    indices: list[int | None] = [None] if frames is None else list(range(frames))
    images: dict[int, np.ndarray] = {}
    seconds: dict[int, float] = {}
    for spp in counts:
        stack, times = [], []
        for frame in indices:
            file = ladder_file(scene, spp, frame)
            path, entry = ladder_dir / file, entry_path(ladder_dir, file)
            if not (path.is_file() and entry.is_file()):
                raise DataError(
                    f"{path}: not found; the spp-equivalent of {scene} reads its ladder of plain renders "
                    "(dataset.ladder_spp): run stage=render with this config's task.eval.split, or set "
                    "metrics.spp_equivalent.enabled=false"
                )
            channels = read_exr(path, ("R", "G", "B"))
            stack.append(np.stack([channels[c] for c in "RGB"], axis=-1).astype(np.float32))
            seconds_of_rung = json.loads(entry.read_text())["seconds"]
            times.append(np.nan if seconds_of_rung is None else float(seconds_of_rung))
        images[int(spp)] = np.stack(stack)
        seconds[int(spp)] = float(np.mean(times))
    return Ladder(scene, images, seconds)
