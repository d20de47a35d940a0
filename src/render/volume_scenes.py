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

Builders return a scene dict *without* integrator and film size, as the surface family does. The cameras
and their motion vectors are ``src/render/volume_camera.py``'s, the media ``src/render/volume_media.py``'s;
this module puts them in scenes with the lights and surfaces. Each scene draws from three independent
random streams of its seed (layout, camera, media), so the camera of a frame (``camera_at``) is known
without building the grids, and no frame index changes a draw.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Mapping

import mitsuba as mi
import numpy as np

from src.errors import ConfigError
from src.render.scenes import (
    WORLD_UP,
    base_constants,
    draw_uniform,
    scatter_objects,
    sky_envmap,
    tabletop,
    textured_ground,
)
from src.render.volume_camera import Camera, camera_path
from src.render.volume_media import cloud_medium, fog_medium, haze_medium, medium_box, plume_medium

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


# --- lights and surfaces -----------------------------------------------------------------------------------


def _sky(rng: np.random.Generator, rnd: Mapping, scale: float) -> dict:
    """The surface family's HDR sky without its sun disc (the sun is a directional light here)."""
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(sky_envmap(rng, {**rnd, "sun_radius_deg": 0.0})),
        "to_world": mi.ScalarTransform4f().rotate(WORLD_UP, draw_uniform(rng, rnd["env_rotation"])),
        "scale": float(scale),
    }


def _sun(rng: np.random.Generator, rnd: Mapping, sun: Mapping) -> dict:
    """A directional sun ``sun.zenith_angle`` degrees from the zenith, at a random azimuth, of irradiance
    ``sun.irradiance``."""
    zenith = np.radians(draw_uniform(rng, sun["zenith_angle"]))
    azimuth = np.radians(draw_uniform(rng, rnd["azimuth"]))
    to_sun = [np.sin(zenith) * np.sin(azimuth), np.cos(zenith), np.sin(zenith) * np.cos(azimuth)]
    return {
        "type": "directional",
        "direction": [-float(c) for c in to_sun],
        "irradiance": {"type": "rgb", "value": draw_uniform(rng, sun["irradiance"])},
    }


def _canopy(rng: np.random.Generator, canopy: Mapping) -> dict:
    """Parallel slats (thin boxes) ``canopy.height`` above the ground, spanning ``canopy.size`` (half-width)
    with random widths and gaps, turned by a random angle about +Y: the occluder the sun shines through."""
    n = int(rng.integers(canopy["slats"][0], canopy["slats"][1] + 1))
    half, height = float(canopy["size"]), float(canopy["height"])
    turn = float(rng.uniform(0, 180))
    slats = {}
    for k, z in enumerate(np.linspace(-half, half, n)):
        width = draw_uniform(rng, canopy["slat_width"])
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


def _sunlit_ground(rng: np.random.Generator, rnd: Mapping, base: Mapping) -> dict:
    """The open-air start of ``cloud`` and ``godrays``: a textured ground (``base.ground``), the sky
    (``base.sky_scale``) and a directional sun (``base.sun``), drawn in that order."""
    return {
        "type": "scene",
        "ground": textured_ground(rng, rnd, base["ground"]),
        "sky": _sky(rng, rnd, float(base["sky_scale"])),
        "sun": _sun(rng, rnd, base["sun"]),
    }


def cloud(rng: np.random.Generator, rnd: Mapping, base: Mapping, media: Callable[[Mapping], dict]) -> dict:
    """A thick cloud in a null-BSDF box above a textured ground, lit by a sun and a sky."""
    scene = _sunlit_ground(rng, rnd, base)
    med = base["medium"]
    box = medium_box(med["box"])
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
    scene = _sunlit_ground(rng, rnd, base)
    scene.update(scatter_objects(rng, rnd, base["objects"]))
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
    return camera_path(_rng(base, seed, CAMERA), ds["randomize"], constants["camera"], frame)


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
