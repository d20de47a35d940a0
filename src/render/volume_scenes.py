"""A procedural family of animated heterogeneous-media scenes: clouds, smoke, height fog and god-ray haze.

After the production volumes of Pixar/Disney's "Denoising Production Volumetric Rendering" (SIGGRAPH 2023
talk: thick FX volumes such as clouds and smoke, thin atmospheric fog) and the volumetric path-tracing
denoising data of Zhang et al. 2022. Like the surface family (``src/render/scenes.py``, whose builders and
materials the table-top bases reuse), a few base scenes are permuted by a seed, every range read from
``dataset.randomize`` and each base's constants from ``dataset.base_scenes.<base>``; here each scene is
also an *animation* of ``dataset.frames`` frames: the camera orbits and dollies smoothly, and the media
drift with a wind (the noise domain is advected) and evolve (the fBm moves along a 4th, time axis).

Bases:

* ``cloud``: a thick cumulus (fBm eroded, Worley-billowed density, high albedo, forward HG phase) in a
  null-BSDF box (its ``interior`` medium), lit by a directional sun and a sky over a textured ground.
* ``smoke_tabletop``: a swaying smoke plume rising from the surface family's table top with its still life
  and area light.
* ``fog_objects``: objects on a ground in exponential height fog lit by an area light and a dim sky.
* ``godrays``: thin haze, a sun through a slatted canopy (shafts of light), objects on a ground.

The fog, smoke and haze contain the camera and the surfaces, so they are one scene-wide medium: the
sensor's ``medium`` and every surface's ``exterior`` refer to it (``ATMOSPHERE``), and paths stay in it
after bouncing off a surface; its density grid is zero outside its box. Grids are numpy arrays
(``src/render/volume_grids.py``) handed to Mitsuba as ``gridvolume`` via ``mi.VolumeGrid`` (no files),
density as ``sigma_t`` (times the medium's ``scale``) and an RGB ``albedo`` grid.

Builders return a scene dict *without* integrator and film size, as the surface family does. Each scene
draws from three independent random streams of its seed (layout, camera, media), so the camera of a
frame (``camera_at``) is known without building the grids, and no frame index changes a draw.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import mitsuba as mi
import numpy as np

from src.errors import ConfigError
from src.render import volume_grids as vg
from src.render.scenes import (
    WORLD_UP,
    _color,
    _ground,
    _objects,
    _uniform,
    base_constants,
    sky_envmap,
    tabletop,
)

#: Id of the scene-wide medium that the sensor and the surfaces of fog, smoke and haze scenes refer to.
ATMOSPHERE = "atmosphere"
#: Random streams of a seed: ``np.random.default_rng([seed, stream, crc32(base)])``.
LAYOUT, CAMERA, MEDIA = 0, 1, 2


def _rng(base: str, seed: int, stream: int) -> np.random.Generator:
    """Stream ``stream`` of ``seed`` for base ``base``: bases of one seed draw different textures and
    layouts, and a frame's camera never depends on how many draws its grids took."""
    return np.random.default_rng([int(seed), stream, zlib.crc32(base.encode())])


def _ref(name: str) -> dict:
    return {"type": "ref", "id": name}


# --- camera ------------------------------------------------------------------------------------------------


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


def _camera_path(rng: np.random.Generator, rnd: Mapping, cam: Mapping, frame: float) -> Camera:
    """A camera orbiting a jittered target: starting azimuth, elevation (``cam.elevation``), distance and
    fov drawn once per seed; the azimuth advances ``orbit_speed`` degrees per frame and the distance
    changes by a factor exp(``dolly_speed`` * frame) (a smooth dolly that never crosses the target)."""
    jitter = float(cam["target_jitter"])
    target = np.array(
        [rng.uniform(-jitter, jitter), float(cam["target_height"]), rng.uniform(-jitter, jitter)]
    )
    azimuth0 = _uniform(rng, rnd["azimuth"])
    elevation = np.radians(_uniform(rng, cam["elevation"]))
    distance0 = float(cam["distance"]) * _uniform(rng, rnd["camera_distance"])
    fov = _uniform(rng, rnd["fov"])
    orbit, dolly = _uniform(rng, rnd["orbit_speed"]), _uniform(rng, rnd["dolly_speed"])
    azimuth = np.radians(azimuth0 + orbit * frame)
    d = distance0 * np.exp(dolly * frame)
    origin = target + d * np.array(
        [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
    )
    return Camera(look_at(origin, target), fov)


# --- media -------------------------------------------------------------------------------------------------


def _box(block: Mapping, centre_offset=(0.0, 0.0, 0.0)) -> vg.Box:
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
    speed, heading = _uniform(rng, rnd["wind_speed"]), np.radians(_uniform(rng, rnd["wind_azimuth"]))
    wind = speed * np.array([np.cos(heading), 0.0, np.sin(heading)])
    evolve = _uniform(rng, rnd["evolve_speed"])
    density_scale = _uniform(rng, med["density_scale"])
    grey = sorted([_uniform(rng, med["albedo"]), _uniform(rng, med["albedo"])])
    tint = np.array(_color(rng, rnd["albedo_tint"]))
    low, high = (list(np.clip(g * tint, 0.0, 1.0)) for g in grey)
    g = _uniform(rng, med["g"])
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
    coverage = _uniform(rng, med["coverage"])
    box = _box(med["box"])
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
    box = _box(med["box"], (rng.uniform(-j, j), 0.0, rng.uniform(-j, j)))
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
    box = _box(med["box"])
    p = vg.voxel_centres(box, vg.grid_shape(box, grid_res))
    points = _noise_points(p, draw, float(med["feature_size"]), frame)
    noise = vg.fbm(points, draw.lattices, float(med["persistence"]), time=draw.evolve * frame)
    return box, p, noise


def fog_medium(rng: np.random.Generator, rnd: Mapping, med: Mapping, grid_res: int, frame: float) -> dict:
    """Height fog over ``med.box``: exp(-h / H) above the box's floor (H from ``med.scale_height``),
    modulated by drifting fBm (``med.modulation``)."""
    draw = _draw_medium(rng, rnd, med)
    scale_height = _uniform(rng, med["scale_height"])
    modulation = _uniform(rng, med["modulation"])
    box, p, noise = _drifting_fbm(draw, med, grid_res, frame)
    density = vg.height_fog_density(p[..., 1] - box.lower[1], scale_height, noise, modulation)
    return _medium_dict(density, _albedo(p, draw, float(med["feature_size"]), frame), box, draw)


def haze_medium(rng: np.random.Generator, rnd: Mapping, med: Mapping, grid_res: int, frame: float) -> dict:
    """Thin, nearly uniform haze over ``med.box`` (fBm ``med.modulation``) for the sun's shafts."""
    draw = _draw_medium(rng, rnd, med)
    modulation = _uniform(rng, med["modulation"])
    box, p, noise = _drifting_fbm(draw, med, grid_res, frame)
    albedo = _albedo(p, draw, float(med["feature_size"]), frame)
    return _medium_dict(vg.haze_density(noise, modulation), albedo, box, draw)


# --- lights and surfaces -----------------------------------------------------------------------------------


def _sky(rng: np.random.Generator, rnd: Mapping, scale: float) -> dict:
    """The surface family's HDR sky without its sun disc (the sun is a directional light here)."""
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(sky_envmap(rng, {**rnd, "sun_radius_deg": 0.0})),
        "to_world": mi.ScalarTransform4f().rotate(WORLD_UP, _uniform(rng, rnd["env_rotation"])),
        "scale": float(scale),
    }


def _sun(rng: np.random.Generator, rnd: Mapping, sun: Mapping) -> dict:
    """A directional sun ``sun.zenith_angle`` degrees from the zenith, at a random azimuth, of irradiance
    ``sun.irradiance``."""
    zenith = np.radians(_uniform(rng, sun["zenith_angle"]))
    azimuth = np.radians(_uniform(rng, rnd["azimuth"]))
    to_sun = [np.sin(zenith) * np.sin(azimuth), np.cos(zenith), np.sin(zenith) * np.cos(azimuth)]
    return {
        "type": "directional",
        "direction": [-float(c) for c in to_sun],
        "irradiance": {"type": "rgb", "value": _uniform(rng, sun["irradiance"])},
    }


def _canopy(rng: np.random.Generator, canopy: Mapping) -> dict:
    """Parallel slats (thin boxes) ``canopy.height`` above the ground, spanning ``canopy.size`` (half-width)
    with random widths and gaps, turned by a random angle about +Y: the occluder the sun shines through."""
    n = int(rng.integers(canopy["slats"][0], canopy["slats"][1] + 1))
    half, height = float(canopy["size"]), float(canopy["height"])
    turn = float(rng.uniform(0, 180))
    slats = {}
    for k, z in enumerate(np.linspace(-half, half, n)):
        width = _uniform(rng, canopy["slat_width"])
        slats[f"slat_{k}"] = {
            "type": "cube",
            "to_world": mi.ScalarTransform4f()
            .rotate(WORLD_UP, turn)
            .translate([0.0, height, float(z)])
            .scale([half, float(canopy["thickness"]), 0.5 * width]),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.3}},
        }
    return slats


def _in_atmosphere(scene: dict, medium: dict) -> dict:
    """``scene`` filled with one scene-wide ``medium``: the sensor's medium and every shape's exterior."""
    scene[ATMOSPHERE] = medium
    for value in scene.values():
        if isinstance(value, dict) and value.get("type") in SHAPE_TYPES:
            value["exterior"] = _ref(ATMOSPHERE)
    return scene


SHAPE_TYPES = {"rectangle", "cube", "sphere", "obj", "ply", "disk", "cylinder"}


# --- base scenes -------------------------------------------------------------------------------------------


def cloud(rng: np.random.Generator, rnd: Mapping, base: Mapping, media: Callable[[Mapping], dict]) -> dict:
    """A thick cloud in a null-BSDF box above a textured ground, lit by a sun and a sky."""
    scene = {
        "type": "scene",
        "ground": _ground(rng, rnd, base["ground"]),
        "sky": _sky(rng, rnd, float(base["sky_scale"])),
        "sun": _sun(rng, rnd, base["sun"]),
    }
    med = base["medium"]
    box = _box(med["box"])
    scene["cloud"] = {
        "type": "cube",
        "to_world": mi.ScalarTransform4f().translate(list(box.centre)).scale([0.5 * s for s in box.size]),
        "bsdf": {"type": "null"},
        "interior": media(med),
    }
    return scene


def _tabletop_in(medium_key: str):
    def build(
        rng: np.random.Generator, rnd: Mapping, base: Mapping, media: Callable[[Mapping], dict]
    ) -> dict:
        scene = tabletop(rng, rnd, base)  # the surface family's table, still life, area light and sky
        scene.pop("sensor")
        return _in_atmosphere(scene, media(base[medium_key]))

    return build


smoke_tabletop = _tabletop_in("medium")
smoke_tabletop.__doc__ = "The surface family's table top with a smoke plume rising from it."
fog_objects = _tabletop_in("medium")
fog_objects.__doc__ = "The table-top layout scaled up to a ground with objects, in height fog, area-lit."


def godrays(rng: np.random.Generator, rnd: Mapping, base: Mapping, media: Callable[[Mapping], dict]) -> dict:
    """Objects on a ground in thin haze, a sun shining through a slatted canopy, and a sky."""
    scene = {
        "type": "scene",
        "ground": _ground(rng, rnd, base["ground"]),
        "sky": _sky(rng, rnd, float(base["sky_scale"])),
        "sun": _sun(rng, rnd, base["sun"]),
    }
    scene.update(_objects(rng, rnd, base["objects"]))
    scene.update(_canopy(rng, base["canopy"]))
    return _in_atmosphere(scene, media(base["medium"]))


#: Each base: (scene builder, medium builder). builder(rng, randomize, base constants, media) -> scene dict,
#: where media(medium block) builds the frame's medium.
BASE_SCENES: dict[str, tuple[Callable, Callable]] = {
    "cloud": (cloud, cloud_medium),
    "smoke_tabletop": (smoke_tabletop, plume_medium),
    "fog_objects": (fog_objects, fog_medium),
    "godrays": (godrays, haze_medium),
}


def _constants(base: str, ds: Mapping) -> Mapping:
    return base_constants(base, ds, BASE_SCENES)


def _check_frame(frame: float, ds: Mapping) -> None:
    frames = int(ds["frames"])
    if not 0 <= frame <= frames - 1:
        raise ConfigError(
            f"frame {frame}: outside the animation; expected 0 <= frame <= dataset.frames - 1 = {frames - 1}"
        )


def camera_at(base: str, seed: int, frame: float, ds: Mapping) -> Camera:
    """The camera of frame ``frame`` (0 .. ``dataset.frames`` - 1; fractions in between are on the same
    smooth path) of base ``base`` permuted by ``seed``: the sensor of ``build_volumetric_frame``."""
    constants = _constants(base, ds)
    _check_frame(frame, ds)
    return _camera_path(_rng(base, seed, CAMERA), ds["randomize"], constants["camera"], frame)


def build_volumetric_frame(base: str, seed: int, frame: float, ds: Mapping) -> dict:
    """The scene dict of frame ``frame`` of base ``base`` permuted by ``seed``, from the dataset config
    ``ds`` (``randomize``, ``base_scenes.<base>``, ``grid_res``, ``frames``). Same arguments, same scene;
    the layout, lights and materials are the same in every frame of a seed, the camera and media move."""
    constants = _constants(base, ds)
    _check_frame(frame, ds)
    rnd, grid_res = ds["randomize"], int(ds["grid_res"])
    builder, medium = BASE_SCENES[base]
    media_rng = _rng(base, seed, MEDIA)
    scene = builder(
        _rng(base, seed, LAYOUT), rnd, constants, lambda med: medium(media_rng, rnd, med, grid_res, frame)
    )
    sensor = camera_at(base, seed, frame, ds).sensor()
    if ATMOSPHERE in scene:
        sensor["medium"] = _ref(ATMOSPHERE)
    scene["sensor"] = sensor
    return scene


def strip_media(scene: dict) -> dict:
    """A copy of a scene dict without its participating media: the scene-wide medium and its references,
    and the null-BSDF boxes holding an interior medium (for comparisons and surface-only renders)."""
    out = {}
    for key, value in scene.items():
        if key == ATMOSPHERE or (
            isinstance(value, dict) and "interior" in value and value.get("bsdf", {}).get("type") == "null"
        ):
            continue
        if isinstance(value, dict):
            value = {k: v for k, v in value.items() if k not in ("medium", "exterior")}
        out[key] = value
    return out
