"""One view of a multi-view scene: its Mitsuba sensor, its render, and its 8-bit PNG encoding.

Conventions:
- Alpha: Mitsuba's path integrator marks a sample valid (alpha 1) when it hits geometry *or* sees a
  visible environment emitter; with ``hide_emitters`` the environment still lights the scene but
  camera rays that miss all geometry get alpha 0 (a transparent background, as Blender's film).
- Colour: the film's RGB is premultiplied by coverage (misses contribute 0); PNGs store straight colour
  rgb / alpha, clipped to [0, 1], sRGB OETF, round(255 x); alpha round(255 a). The ``box`` pixel filter
  (``rfilter``) makes each pixel the average over its own square, the pixel model of NeRF/mip-NeRF.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from src.io.srgb import srgb_oetf
from src.render.multiview_cameras import mitsuba_to_world


def _transform(matrix=None):
    import mitsuba as mi

    return mi.ScalarTransform4f() if matrix is None else mi.ScalarTransform4f(np.asarray(matrix).tolist())


def make_sensor(ds: Mapping, c2w: np.ndarray):
    """A Mitsuba perspective sensor for the OpenGL camera-to-world ``c2w`` with an RGBA float film."""
    import mitsuba as mi

    return mi.load_dict(
        {
            "type": "perspective",
            "fov_axis": "x",
            "fov": math.degrees(float(ds["camera_angle_x"])),
            "to_world": _transform(mitsuba_to_world(c2w)),
            "film": {
                "type": "hdrfilm",
                "width": int(ds["width"]),
                "height": int(ds["height"]),
                "pixel_format": "rgba",
                "component_format": "float32",
                "rfilter": {"type": str(ds["rfilter"])},
            },
            "sampler": {"type": "independent"},
        }
    )


def render_view(scene, sensor, spp: int, seeds: list[int], passes: list[int]) -> np.ndarray:
    """(H, W, 4) float32 linear RGBA (colour premultiplied by coverage), ``spp`` samples in ``passes``."""
    import mitsuba as mi

    total = None
    for seed, n in zip(seeds, passes, strict=True):
        img = np.asarray(mi.render(scene, sensor=sensor, spp=n, seed=seed), dtype=np.float64) * n
        total = img if total is None else total + img
    return (total / spp).astype(np.float32)


def encode_rgba8(rgba: np.ndarray) -> np.ndarray:
    """Premultiplied linear RGBA (H, W, 4) -> uint8 straight-alpha sRGB RGBA (H, W, 4), as Blender's PNGs."""
    alpha = np.clip(rgba[..., 3:], 0.0, 1.0)
    straight = np.divide(rgba[..., :3], alpha, out=np.zeros_like(rgba[..., :3]), where=alpha > 0)
    colour = srgb_oetf(np.clip(straight, 0.0, 1.0))
    return np.round(np.concatenate([colour, alpha], axis=-1) * 255.0).astype(np.uint8)
