"""The cameras of the volumetric scenes (``src.render.volume_scenes``) and the motion they make: Mitsuba's
look-at and pinhole projection reproduced in numpy, the camera path of an animation (an orbit and a dolly
around a jittered target, drawn once per seed), and the screen-space motion vectors between two frames'
cameras (``src.render.volume_dataset`` writes them as the ``motion`` buffer; the temporal metrics and the
sequence denoisers read them).

Kept apart from the scene builders because they are geometry, not scene content: ``volume_dataset`` needs a
frame's camera and its projection without building a scene, and the projection is tested against
Mitsuba's own camera (tests/test_volume_scenes.py).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from src.render.scenes import WORLD_UP, draw_uniform


def look_at(origin, target, up=WORLD_UP) -> np.ndarray:
    """The 4x4 camera-to-world matrix of Mitsuba's ``look_at``: columns left (+x), up (+y), viewing
    direction (+z) and the origin. Mitsuba's perspective camera maps local +x to the image's *left*."""
    origin, target, up = (np.asarray(v, float) for v in (origin, target, up))
    d = target - origin
    d /= np.linalg.norm(d)
    left = np.cross(up, d)
    left /= np.linalg.norm(left)
    new_up = np.cross(d, left)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = left, new_up, d, origin
    return m


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: ``to_world`` (4x4, Mitsuba's look-at convention) and ``fov`` (degrees, along
    the image's x axis, Mitsuba's ``fov_axis: x``)."""

    to_world: np.ndarray
    fov: float

    @property
    def origin(self) -> np.ndarray:
        return self.to_world[:3, 3]

    def sensor(self) -> dict:
        """The Mitsuba ``perspective`` sensor dict (no film: the renderer sets the size)."""
        return {
            "type": "perspective",
            "fov": float(self.fov),
            "fov_axis": "x",
            "to_world": mi.ScalarTransform4f(self.to_world.tolist()),
        }


def project(points: np.ndarray, camera: Camera, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (..., 2) and camera depth (...) of world ``points`` (..., 3) seen by ``camera`` on
    a ``width`` x ``height`` film: x to the right, y down, the top-left pixel spanning [0, 1)^2 (its centre
    at (0.5, 0.5)), as Mitsuba's perspective camera samples them. Depth <= 0: behind the camera."""
    inv = np.linalg.inv(camera.to_world)
    tan_half = np.tan(np.radians(camera.fov) / 2)
    aspect = width / height
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):  # no surface (inf) or depth 0: NaN
        local = points @ inv[:3, :3].T + inv[:3, 3]
        z = local[..., 2]
        x = local[..., 0] / (z * tan_half)
        y = local[..., 1] / (z * tan_half)
    return np.stack([(1 - x) / 2 * width, (1 - aspect * y) / 2 * height], -1), z


def motion_vectors(
    world_positions_t: np.ndarray, camera_t: Camera, camera_t1: Camera, width: int, height: int
) -> np.ndarray:
    """(H, W, 2) screen-space motion from frame t to t+1 of the surfaces seen at frame t.

    ``world_positions_t`` (H, W, 3) are the world positions seen through each pixel at frame t (static
    geometry: only the camera moves). Each is projected by ``camera_t`` and by ``camera_t1`` (``project``);
    the flow is the difference, in pixels, +x to the right, +y down, from t to t+1: the pixel at p in frame
    t shows its surface at p + flow in frame t+1. NaN where a position is not finite (no surface: sky,
    pure media) or lies behind either camera, so a consumer masks with ``np.isfinite``."""
    p = np.asarray(world_positions_t, float)
    if p.shape != (height, width, 3):
        raise ValueError(f"world_positions_t: shape {p.shape}; expected ({height}, {width}, 3)")
    at_t, z_t = project(p, camera_t, width, height)
    at_t1, z_t1 = project(p, camera_t1, width, height)
    flow = at_t1 - at_t
    bad = ~np.isfinite(p).all(-1) | ~(z_t > 0) | ~(z_t1 > 0)
    flow[bad] = np.nan
    return flow


def camera_path(rng: np.random.Generator, rnd: Mapping, cam: Mapping, frame: float) -> Camera:
    """A camera orbiting a jittered target: starting azimuth, elevation (``cam.elevation``), distance and
    fov drawn once per seed; the azimuth advances ``orbit_speed`` degrees per frame and the distance
    changes by a factor exp(``dolly_speed`` * frame) (a smooth dolly that never crosses the target)."""
    jitter = float(cam["target_jitter"])
    target = np.array(
        [rng.uniform(-jitter, jitter), float(cam["target_height"]), rng.uniform(-jitter, jitter)]
    )
    azimuth0 = draw_uniform(rng, rnd["azimuth"])
    elevation = np.radians(draw_uniform(rng, cam["elevation"]))
    distance0 = float(cam["distance"]) * draw_uniform(rng, rnd["camera_distance"])
    fov = draw_uniform(rng, rnd["fov"])
    orbit, dolly = draw_uniform(rng, rnd["orbit_speed"]), draw_uniform(rng, rnd["dolly_speed"])
    azimuth = np.radians(azimuth0 + orbit * frame)
    d = distance0 * np.exp(dolly * frame)
    origin = target + d * np.array(
        [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
    )
    return Camera(look_at(origin, target), fov)
