"""The structured studio environment map that lights the ``spheres`` multi-view scene."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

#: Mitsuba's envmap is +y up; this rotation (about +x by 90 degrees) maps its +y onto the world's +z.
ENVMAP_UP_ROTATION = ([1.0, 0.0, 0.0], 90.0)


def studio_envmap(env: Mapping) -> np.ndarray:
    """A high-contrast latitude-longitude HDR environment (res x 2 res x 3, +y up, Mitsuba's layout).

    Sky gradient (``horizon`` to ``zenith``) above a dark ``ground``; ``stripes.count`` tall bright
    panels (soft boxes) evenly spaced in azimuth between ``stripes.elevation_deg``, coloured in turn by
    ``stripes.colors``; and a small intense ``sun`` disc. Sharp, coloured structure, so glossy
    reflections change visibly with the viewpoint. Elevations are above the map's horizon (world
    xy plane once rotated +z up); azimuths are along the map's u axis (shift them all with
    ``rotation_deg``).
    """
    h = int(env["res"])
    w = 2 * h
    theta = (np.arange(h) + 0.5) / h * np.pi  # polar angle from +y
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    elevation = np.degrees(np.pi / 2 - theta)[:, None] * np.ones((1, w))
    azimuth = np.degrees(phi)[None, :] * np.ones((h, 1))
    t = np.clip(np.cos(theta), 0.0, 1.0)[:, None, None]
    horizon, zenith, ground = (np.asarray(env[k], np.float64) for k in ("horizon", "zenith", "ground"))
    sky = np.where(elevation[..., None] > 0, horizon * (1 - t) + zenith * t, ground)
    stripes = env["stripes"]
    count = int(stripes["count"])
    if count > 0:
        period = 360.0 / count
        offset = (azimuth % period) < float(stripes["width_deg"])
        lo, hi = stripes["elevation_deg"]
        band = offset & (elevation >= lo) & (elevation <= hi)
        colors = np.asarray(stripes["colors"], np.float64).reshape(-1, 3)
        which = (azimuth // period).astype(int) % len(colors)
        sky = np.where(band[..., None], colors[which] * float(stripes["intensity"]), sky)
    sun = env["sun"]
    dirs = np.stack(
        [
            np.sin(theta)[:, None] * np.cos(phi),
            np.cos(theta)[:, None] * np.ones((1, w)),
            np.sin(theta)[:, None] * np.sin(phi),
        ],
        axis=-1,
    )
    s_theta, s_phi = math.radians(90.0 - float(sun["elevation_deg"])), math.radians(float(sun["azimuth_deg"]))
    sun_dir = np.array(
        [math.sin(s_theta) * math.cos(s_phi), math.cos(s_theta), math.sin(s_theta) * math.sin(s_phi)]
    )
    disc = dirs @ sun_dir > math.cos(math.radians(float(sun["radius_deg"])))
    sky[disc] = float(sun["intensity"])
    return (sky * float(env["scale"])).astype(np.float32)


def envmap_emitter(env: Mapping) -> dict:
    import mitsuba as mi

    axis, angle = ENVMAP_UP_ROTATION
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(studio_envmap(env)),
        "to_world": mi.ScalarTransform4f().rotate([0, 0, 1], float(env["rotation_deg"])).rotate(axis, angle),
    }
