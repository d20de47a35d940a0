"""Volumetric sequence EXRs: the channel layout, the file naming and the grouping into sequences.

One EXR per (scene, frame, sample count), ``<scene>-f<FFFF>-<NNNNN>spp.exr`` (e.g.
``cloud-0000-f0003-00016spp.exr``), holding every buffer of the volumetric path tracer
(``src.data.volume_aovs.CHANNEL_COUNT``, ``color`` first) as flat channels in the KPCN/Tungsten style:

* ``R,G,B``: ``color`` (= ``surface`` + ``volume``);
* ``<buffer>.R/G/B``: three-channel colours and spectral quantities (``surface``, ``volume``,
  ``volume_single``, ``volume_multi``, ``albedo``, ``transmittance``, ``optical_thickness``, ``sigma_t``,
  ``sigma_s``, ``scatter_albedo``) and ``normal`` (as in the KPCN files);
* ``<buffer>.X/Y/Z``: world-space points (``position``, ``scatter_position``);
* ``<buffer>.Z``: one-channel buffers (``depth``, ``visibility``, ``scatter_depth``,
  ``scatter_media_distance``, ``scattered``, ``volume_events``);
* ``motion.X/Y``: screen-space motion in pixels (see ``src.render.volume_dataset.frame_motion``);
* ``<buffer>Variance.Z``: for every rendered buffer (``motion`` has none), the variance of the pixel mean
  averaged over the buffer's channels, as in the KPCN data (``src.render.moments.variance_of_mean``).

It is one `BufferLayout` of ``src.data.exr_buffers``: `load_volume_exr` checks every file against it
(every channel present, one size, finite, non-negative radiance and variance).
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType

from src.data.exr_buffers import BufferLayout
from src.data.volume_aovs import CHANNEL_COUNT, MOMENT_BUFFERS
from src.errors import DataError

_RGB = ("R", "G", "B")
_XYZ = ("X", "Y", "Z")
#: Three-channel buffers that are world-space points: channels X/Y/Z (other three-channel ones: R/G/B).
POINT_BUFFERS = ("position", "scatter_position")
#: Radiance buffers (never negative): the colour and its surface / volume split.
VOLUME_RADIANCE = ("color", "surface", "volume", "volume_single", "volume_multi")
#: The motion buffer (not rendered: computed from ``position`` and the cameras), its channels.
MOTION_CHANNELS = ("motion.X", "motion.Y")


def _channels(buf: str, n: int) -> tuple[str, ...]:
    if buf == "color":
        return _RGB
    if n == 1:
        return (f"{buf}.Z",)
    if n == 3:
        return tuple(f"{buf}.{c}" for c in (_XYZ if buf in POINT_BUFFERS else _RGB))
    raise ValueError(f"volumetric buffer {buf!r} has {n} channels; the EXR naming knows 1 and 3")


VOLUME_EXR_BUFFERS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        **{buf: _channels(buf, n) for buf, n in CHANNEL_COUNT.items()},
        "motion": MOTION_CHANNELS,
        **{f"{buf}Variance": (f"{buf}Variance.Z",) for buf in MOMENT_BUFFERS},
    }
)
"""Buffer name -> EXR channel names, in the order of the last axis of the (H, W, C) array."""

VOLUME_VARIANCE = tuple(b for b in VOLUME_EXR_BUFFERS if b.endswith("Variance"))
VOLUME_LAYOUT = BufferLayout(
    "volumetric", VOLUME_EXR_BUFFERS, radiance=VOLUME_RADIANCE, variance=VOLUME_VARIANCE
)


#: One volumetric EXR in the `VOLUME_LAYOUT` naming: load and validate (`load_buffers`), write (atomically).
load_volume_exr = VOLUME_LAYOUT.load
write_volume_exr = VOLUME_LAYOUT.write


# --- file naming -------------------------------------------------------------------------------------------

_VOLUME_EXR_NAME = re.compile(r"^(?P<scene>.+)-f(?P<frame>\d+)-(?P<spp>\d+)spp\.exr$")


#: Sub-folder of the raw folder holding the second, independent reference of the held-out scenes
#: (``dataset.second_reference``), named like the others: ``<raw>/reference2/<scene>-f<FFFF>-<NNNNN>spp.exr``
#: (with its own ``manifest/``). A folder of its own, so that `group_volume_dataset` (the raw folder's
#: ``*.exr``) never takes a second reference for a sample count of the sequence.
SECOND_REFERENCE_DIR = "reference2"


def volume_exr_name(scene: str, frame: int, spp: int) -> str:
    """The file of one render: ``<scene>-f<FFFF>-<NNNNN>spp.exr`` (inverse of `parse_volume_exr_name`)."""
    return f"{scene}-f{frame:04d}-{spp:05d}spp.exr"


def parse_volume_exr_name(path: str | os.PathLike[str]) -> tuple[str, int, int]:
    """``<scene>-f<FFFF>-<NNNNN>spp.exr`` -> (scene, frame, spp); the scene may contain dashes."""
    m = _VOLUME_EXR_NAME.match(Path(path).name)
    if m is None or int(m["spp"]) < 1:
        raise DataError(f"{path}: expected a volumetric file name like '<scene>-f0003-00016spp.exr'")
    return m["scene"], int(m["frame"]), int(m["spp"])


def group_volume_dataset(raw_dir: str | os.PathLike[str]) -> dict[str, dict[int, dict[int, Path]]]:
    """{scene: {frame: {spp: path}}} for every ``*.exr`` in ``raw_dir``, sorted at every level.

    Every scene must be a whole sequence (frames 0 .. n-1, none missing), rendered at the same sample
    counts in every frame, and at two or more of them (noisy inputs plus the reference, the highest);
    otherwise a one-line DataError names the scene and what is missing.
    """
    raw_dir = Path(raw_dir)
    if not raw_dir.is_dir():
        raise DataError(f"{raw_dir}: raw data directory does not exist")
    groups: dict[str, dict[int, dict[int, Path]]] = {}
    for path in sorted(raw_dir.glob("*.exr")):
        scene, frame, spp = parse_volume_exr_name(path)
        groups.setdefault(scene, {}).setdefault(frame, {})[spp] = path
    if not groups:
        raise DataError(f"{raw_dir}: no '<scene>-f<FFFF>-<NNNNN>spp.exr' files found")
    out = {}
    for scene in sorted(groups):
        frames = groups[scene]
        missing = sorted(set(range(max(frames) + 1)) - set(frames))
        if missing:
            raise DataError(f"{raw_dir}: scene {scene!r} lacks frame(s) {missing} of frames 0-{max(frames)}")
        counts = sorted(set().union(*(set(f) for f in frames.values())))
        for frame in sorted(frames):
            lacking = sorted(set(counts) - set(frames[frame]))
            if lacking:
                what = " (the reference)" if counts[-1] in lacking else ""
                raise DataError(
                    f"{raw_dir}: scene {scene!r} frame {frame} lacks the {lacking} spp render(s){what} that "
                    "other frames have"
                )
        if len(counts) < 2:
            raise DataError(
                f"{raw_dir}: scene {scene!r} has a single sample count ({counts[0]} spp); each frame needs "
                "noisy render(s) and a higher-spp reference"
            )
        out[scene] = {f: dict(sorted(frames[f].items())) for f in sorted(frames)}
    return out
