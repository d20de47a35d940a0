"""KPCN/Tungsten EXR buffer convention, shared by our renderer and by real KPCN data users already have.

One EXR per (scene, spp) holds every buffer as flat channels: `R,G,B` (color), `diffuse.R/G/B`, ...,
`depth.Z`, and one-channel variances of the pixel mean (`colorVariance.Z`, ...). It is one
`BufferLayout` of `src.data.exr_buffers`, whose loader checks every file against it.

Our renderer also writes the features of the genetic-programming filters (Davletaliyev 2016, Sec. 3.2.1.2):
`position.R/G/B` (world position of the first hit; 3-vectors use `.R/.G/.B` as `normal` does) and
`secondary_albedo.R/G/B` (albedo at the hit of the mirror-reflected camera ray), with `positionVariance.Z`
and `secondary_albedoVariance.Z`. These are OPTIONAL buffers (`OPTIONAL_BUFFERS`): real KPCN data and our
older renders lack them and still load (without those keys).
"""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

from src.data.exr_buffers import BufferLayout

_RGB = ("R", "G", "B")
KPCN_BUFFERS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        "color": _RGB,
        **{b: tuple(f"{b}.{c}" for c in _RGB) for b in ("diffuse", "specular", "albedo", "normal")},
        "depth": ("depth.Z",),
        "visibility": ("visibility.Z",),
        **{
            f"{b}Variance": (f"{b}Variance.Z",)
            for b in ("color", "diffuse", "specular", "albedo", "normal", "depth", "visibility")
        },
        **{b: tuple(f"{b}.{c}" for c in _RGB) for b in ("position", "secondary_albedo")},
        **{f"{b}Variance": (f"{b}Variance.Z",) for b in ("position", "secondary_albedo")},
    }
)
"""Buffer name -> EXR channel names, in the order of the last axis of the (H, W, C) array."""

#: Buffers a KPCN file may lack (the GP filters' features, rendered by our integrator since they were added).
OPTIONAL_BUFFERS = ("position", "secondary_albedo", "positionVariance", "secondary_albedoVariance")
RADIANCE_BUFFERS = ("color", "diffuse", "specular")
VARIANCE_BUFFERS = tuple(b for b in KPCN_BUFFERS if b.endswith("Variance"))
KPCN_LAYOUT = BufferLayout(
    "KPCN", KPCN_BUFFERS, radiance=RADIANCE_BUFFERS, variance=VARIANCE_BUFFERS, optional=OPTIONAL_BUFFERS
)


#: One KPCN EXR in the Tungsten channel naming: load and validate (`load_buffers`), write (atomically).
load_kpcn_exr = KPCN_LAYOUT.load
write_kpcn_exr = KPCN_LAYOUT.write
