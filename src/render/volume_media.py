"""The animated participating media of the volumetric scenes (``src.render.volume_scenes``): a thick
cloud, a smoke plume, height fog and thin haze, each a density grid and an RGB albedo grid handed to
Mitsuba as a ``heterogeneous`` medium of ``gridvolume``s (``mi.VolumeGrid``, no files).

Each medium draws its per-seed constants once (``MediumDraw``: noise tables, offset, wind, evolution
speed, density scale, albedo range, phase function), so every frame of a seed is the same medium moved
on: the noise domain is advected by the wind and the fBm moves along a 4th, time axis. The densities
themselves (fBm, Worley billows, the cloud's and plume's shapes, exponential height fog) are
``src/render/volume_grids.py``'s.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from src.render import volume_grids as vg
from src.render.scenes import draw_color, draw_uniform


def medium_box(block: Mapping, centre_offset=(0.0, 0.0, 0.0)) -> vg.Box:
    centre = tuple(float(c) + float(o) for c, o in zip(block["centre"], centre_offset, strict=True))
    return vg.Box(centre, tuple(float(s) for s in block["size"]))


@dataclass(frozen=True)
class MediumDraw:
    """The per-seed draws of a medium (independent of the frame)."""

    lattices: np.ndarray  # fBm tables of the density
    albedo_lattices: np.ndarray  # fBm tables of the albedo variation
    offset: np.ndarray  # (3,) noise-domain offset
    wind: np.ndarray  # (3,) scene units per frame
    evolve: float  # noise time per frame
    density_scale: float
    albedo_low: list[float]
    albedo_high: list[float]
    phase: dict


def _draw_medium(rng: np.random.Generator, rnd: Mapping, med: Mapping) -> MediumDraw:
    lattices = vg.noise_lattices(rng, int(med["octaves"]))
    albedo_lattices = vg.noise_lattices(rng, 2)
    offset = rng.uniform(0, vg.LATTICE_PERIOD, 3)
    speed, heading = draw_uniform(rng, rnd["wind_speed"]), np.radians(draw_uniform(rng, rnd["wind_azimuth"]))
    wind = speed * np.array([np.cos(heading), 0.0, np.sin(heading)])
    evolve = draw_uniform(rng, rnd["evolve_speed"])
    density_scale = draw_uniform(rng, med["density_scale"])
    grey = sorted([draw_uniform(rng, med["albedo"]), draw_uniform(rng, med["albedo"])])
    tint = np.array(draw_color(rng, rnd["albedo_tint"]))
    low, high = (list(np.clip(g * tint, 0.0, 1.0)) for g in grey)
    g = draw_uniform(rng, med["g"])
    isotropic = rng.random() < float(rnd["isotropic_probability"])
    phase = {"type": "isotropic"} if isotropic else {"type": "hg", "g": g}
    return MediumDraw(lattices, albedo_lattices, offset, wind, evolve, density_scale, low, high, phase)


def _noise_points(
    p: np.ndarray, draw: MediumDraw, feature: float, frame: float, extra_wind=0.0
) -> np.ndarray:
    """Noise-domain coordinates of world points ``p`` at ``frame``: advected by the wind (plus
    ``extra_wind``, e.g. a plume's rise), in units of the feature size, offset per seed."""
    return (p - (draw.wind + extra_wind) * frame) / feature + draw.offset


def _medium_dict(density: np.ndarray, albedo: np.ndarray, box: vg.Box, draw: MediumDraw) -> dict:
    """A Mitsuba ``heterogeneous`` medium: the density grid as ``sigma_t`` (times ``scale``) and the RGB
    albedo grid, both ``gridvolume``s over ``box``."""
    to_world = mi.ScalarTransform4f(vg.box_to_world(box).tolist())
    return {
        "type": "heterogeneous",
        "sigma_t": {
            "type": "gridvolume",
            "grid": mi.VolumeGrid(density.astype(np.float32)),
            "to_world": to_world,
        },
        "albedo": {
            "type": "gridvolume",
            "grid": mi.VolumeGrid(albedo.astype(np.float32)),
            "to_world": to_world,
        },
        "scale": draw.density_scale,
        "phase": dict(draw.phase),
    }


def _albedo(p: np.ndarray, draw: MediumDraw, feature: float, frame: float) -> np.ndarray:
    noise = vg.fbm(_noise_points(p, draw, 2.0 * feature, frame) + 5.0, draw.albedo_lattices, 0.5)
    return vg.albedo_grid(noise, draw.albedo_low, draw.albedo_high)


def cloud_medium(rng: np.random.Generator, rnd: Mapping, med: Mapping, grid_res: int, frame: float) -> dict:
    """The thick cloud: ``cloud_density`` over ``med.box``, its Worley billows at ``med.worley_cells``
    cells per feature size, advected by the wind and evolving in time."""
    draw = _draw_medium(rng, rnd, med)
    features = vg.worley_points(rng, vg.LATTICE_PERIOD)
    coverage = draw_uniform(rng, med["coverage"])
    box = medium_box(med["box"])
    p = vg.voxel_centres(box, vg.grid_shape(box, grid_res))
    feature = float(med["feature_size"])
    pts = _noise_points(p, draw, feature, frame)
    shape = vg.fbm(pts, draw.lattices, float(med["persistence"]), time=draw.evolve * frame)
    billows = 1.0 - np.clip(vg.worley(pts * float(med["worley_cells"]), features), 0.0, 1.0)
    local = (p - np.asarray(box.centre)) / (0.5 * np.asarray(box.size))
    density = vg.cloud_density(local, shape, billows, coverage, float(med["softness"]))
    return _medium_dict(density, _albedo(p, draw, feature, frame), box, draw)


def plume_medium(rng: np.random.Generator, rnd: Mapping, med: Mapping, grid_res: int, frame: float) -> dict:
    """A smoke plume over its source (``med.box`` moved by up to ``med.source_jitter`` in x and z): noise
    rising at ``med.rise_speed`` per frame (plus the wind), a centre line swaying by up to ``med.sway`` box
    half-widths at the top."""
    draw = _draw_medium(rng, rnd, med)
    sway_lattice = vg.noise_lattices(rng, 1)[0]
    j = float(med["source_jitter"])
    box = medium_box(med["box"], (rng.uniform(-j, j), 0.0, rng.uniform(-j, j)))
    p = vg.voxel_centres(box, vg.grid_shape(box, grid_res))
    feature = float(med["feature_size"])
    rise = np.array([0.0, float(med["rise_speed"]), 0.0])
    t = draw.evolve * frame
    noise = vg.fbm(
        _noise_points(p, draw, feature, frame, rise), draw.lattices, float(med["persistence"]), time=t
    )
    local = (p - np.asarray(box.centre)) / (0.5 * np.asarray(box.size))
    h = 0.5 * (local[..., 1] + 1.0)
    # The centre line wanders with height and time: 1-D value noise along (height - rise, time) per axis.
    shift = h * (2.0 * float(med["box"]["size"][1]) / feature) - float(med["rise_speed"]) * frame / feature
    sway = np.stack(
        [
            vg.value_noise_nd(
                np.stack([shift, np.full_like(h, a * 7.0), np.zeros_like(h), np.full_like(h, t)], -1),
                sway_lattice,
            )
            for a in (0, 1)
        ],
        -1,
    )
    sway = (2.0 * sway - 1.0) * float(med["sway"]) * h[..., None]
    density = vg.plume_density(
        local, noise, float(med["radius"]), float(med["spread"]), sway, float(med["detail"])
    )
    return _medium_dict(density, _albedo(p, draw, feature, frame), box, draw)


def _drifting_fbm(draw, med: Mapping, grid_res: int, frame: float):
    """(box, voxel centres, fBm at frame ``frame``) of a thin medium's modulation over ``med.box``: the
    noise domain drifts with the wind and evolves in time (fog and haze share it)."""
    box = medium_box(med["box"])
    p = vg.voxel_centres(box, vg.grid_shape(box, grid_res))
    points = _noise_points(p, draw, float(med["feature_size"]), frame)
    noise = vg.fbm(points, draw.lattices, float(med["persistence"]), time=draw.evolve * frame)
    return box, p, noise


def fog_medium(rng: np.random.Generator, rnd: Mapping, med: Mapping, grid_res: int, frame: float) -> dict:
    """Height fog over ``med.box``: exp(-h / H) above the box's floor (H from ``med.scale_height``),
    modulated by drifting fBm (``med.modulation``)."""
    draw = _draw_medium(rng, rnd, med)
    scale_height = draw_uniform(rng, med["scale_height"])
    modulation = draw_uniform(rng, med["modulation"])
    box, p, noise = _drifting_fbm(draw, med, grid_res, frame)
    density = vg.height_fog_density(p[..., 1] - box.lower[1], scale_height, noise, modulation)
    return _medium_dict(density, _albedo(p, draw, float(med["feature_size"]), frame), box, draw)


def haze_medium(rng: np.random.Generator, rnd: Mapping, med: Mapping, grid_res: int, frame: float) -> dict:
    """Thin, nearly uniform haze over ``med.box`` (fBm ``med.modulation``) for the sun's shafts."""
    draw = _draw_medium(rng, rnd, med)
    modulation = draw_uniform(rng, med["modulation"])
    box, p, noise = _drifting_fbm(draw, med, grid_res, frame)
    albedo = _albedo(p, draw, float(med["feature_size"]), frame)
    return _medium_dict(vg.haze_density(noise, modulation), albedo, box, draw)
