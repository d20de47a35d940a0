"""Camera poses of the multi-view scenes, as OpenGL camera-to-world matrices, and their Mitsuba form.

Conventions:
- World: +z up, like Blender. Cameras sit at distance ``radius`` from the origin and look at it; train
  and val positions are uniform (by area) on the spherical zone between ``elevation_range_deg``, test
  views follow a circle at ``test_elevation_deg`` (evenly spaced azimuths), like the original scenes.
- ``transform_matrix`` is the OpenGL camera-to-world: columns are the camera's right (+x), up (+y) and
  back (+z; the camera looks down -z) axes and its position. Mitsuba's ``look_at`` frame has columns
  (left, up, forward), its image x growing towards -left: Mitsuba's to_world = c2w @ diag(-1, 1, -1, 1).
  Both the Mitsuba sensor and the JSON are made from the one c2w, so they cannot disagree.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from src.errors import ConfigError
from src.render.multiview_seeds import split_seed

#: Camera ``up`` hint of the world (+z, Blender's convention), and the fallback when looking along it.
WORLD_UP = np.array([0.0, 0.0, 1.0])
FALLBACK_UP = np.array([0.0, 1.0, 0.0])
#: OpenGL camera axes (right, up, back) -> Mitsuba camera axes (left, up, forward).
GL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])


def look_at_c2w(position, target=(0.0, 0.0, 0.0), up=WORLD_UP) -> np.ndarray:
    """(4, 4) OpenGL camera-to-world of a camera at ``position`` looking at ``target`` (up hint ``up``)."""
    position, target = np.asarray(position, np.float64), np.asarray(target, np.float64)
    back = position - target
    norm = np.linalg.norm(back)
    if norm == 0:
        raise ConfigError(f"camera at {position.tolist()} coincides with its target")
    back /= norm
    up = np.asarray(up, np.float64)
    if np.linalg.norm(np.cross(up, back)) < 1e-6:  # looking straight along the up hint
        up = FALLBACK_UP
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    c2w = np.eye(4)
    c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, np.cross(back, right), back, position
    return c2w


def mitsuba_to_world(c2w: np.ndarray) -> np.ndarray:
    """Mitsuba sensor to_world for an OpenGL camera-to-world (flip the x and z camera axes)."""
    return np.asarray(c2w, np.float64) @ GL_TO_MITSUBA


def sphere_position(radius: float, elevation: float, azimuth: float) -> np.ndarray:
    """Point at ``radius`` with elevation above the xy plane and azimuth from +x (radians), z up."""
    return radius * np.array(
        [
            math.cos(elevation) * math.cos(azimuth),
            math.cos(elevation) * math.sin(azimuth),
            math.sin(elevation),
        ]
    )


def hemisphere_poses(rng: np.random.Generator, n: int, radius: float, elevation_range_deg) -> np.ndarray:
    """(n, 4, 4) cameras uniform by area on the zone between the two elevations, looking at the origin."""
    lo, hi = (math.radians(float(e)) for e in elevation_range_deg)
    if not -math.pi / 2 <= lo <= hi <= math.pi / 2:
        raise ConfigError(
            f"dataset.elevation_range_deg={list(elevation_range_deg)}: expected lo <= hi within [-90, 90]"
        )
    sin_elev = rng.uniform(math.sin(lo), math.sin(hi), n)  # uniform z <=> uniform area on the sphere
    azimuth = rng.uniform(0.0, 2 * math.pi, n)
    return np.stack(
        [
            look_at_c2w(sphere_position(radius, math.asin(s), a))
            for s, a in zip(sin_elev, azimuth, strict=True)
        ]
    )


def circle_poses(n: int, radius: float, elevation_deg: float, azimuth_start_deg: float) -> np.ndarray:
    """(n, 4, 4) cameras evenly spaced on a circle at a fixed elevation, looking at the origin."""
    elevation = math.radians(float(elevation_deg))
    start = math.radians(float(azimuth_start_deg))
    return np.stack(
        [look_at_c2w(sphere_position(radius, elevation, start + 2 * math.pi * k / n)) for k in range(n)]
    )


def split_poses(ds: Mapping, scene: str, split: str) -> np.ndarray:
    """(views, 4, 4) OpenGL camera-to-world matrices of ``split``: random on the zone, or the test circle."""
    n = int(ds["views"][split])
    if split == "test":
        return circle_poses(n, float(ds["radius"]), ds["test_elevation_deg"], ds["test_azimuth_start_deg"])
    rng = np.random.default_rng(split_seed(int(ds["seed"]), scene, split))
    return hemisphere_poses(rng, n, float(ds["radius"]), ds["elevation_range_deg"])
