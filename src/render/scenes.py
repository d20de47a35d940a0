"""A procedural scene family for the denoising dataset, in the spirit of the KPCN set.

Bako et al. permuted 8 base scenes into ~1500 by varying camera, materials and lighting. Here a few
base scenes are built with ``mi.load_dict`` and permuted by a seed: camera position, target and
field of view, material type and roughness (diffuse, rough conductor, rough dielectric, plastic),
procedural textures (checkerboard / multi-octave value noise bitmaps made on the fly), light
intensity and environment-map rotation. All ranges come from ``dataset.randomize`` in ``conf/``; each
base scene's layout, light and camera constants from ``dataset.base_scenes.<base>``.

Builders return a scene dict *without* integrator and film size: the dataset renderer adds the
AOV integrator and a box-filtered film, so user scene files go through exactly the same path.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import mitsuba as mi
import numpy as np

from src.errors import ConfigError

#: World up (+Y, Mitsuba's convention) of every camera and light ``look_at`` in these scenes.
WORLD_UP = [0, 1, 0]
#: Mitsuba's rectangle faces +Z; this rotation (about +X by -90 degrees) lays it flat, facing +Y.
FLOOR_ROTATION = ([1, 0, 0], -90)


def draw_uniform(rng: np.random.Generator, bounds) -> float:
    """A number uniform in ``bounds`` = [lo, hi] (a scene config's random range)."""
    lo, hi = bounds
    return float(rng.uniform(lo, hi))


def value_noise(
    rng: np.random.Generator, res: int, octaves: int, base_cells: int, persistence: float
) -> np.ndarray:
    """(res, res) fractal value noise in [0, 1]: bilinearly upsampled random lattices of ``base_cells``
    cells per side, doubled per octave, each octave's amplitude ``persistence`` times the previous one's."""
    out = np.zeros((res, res))
    coords = np.linspace(0.0, 1.0, res)
    for o in range(octaves):
        cells = base_cells * 2**o
        lattice = rng.random((cells + 1, cells + 1))
        x = coords * cells
        i = np.minimum(x.astype(int), cells - 1)
        f = x - i
        rows = lattice[i] * (1 - f)[:, None] + lattice[i + 1] * f[:, None]  # interpolate along y
        out += (rows[:, i] * (1 - f) + rows[:, i + 1] * f) * persistence**o  # then along x
    return (out - out.min()) / max(out.max() - out.min(), 1e-12)


def draw_color(rng: np.random.Generator, bounds) -> list[float]:
    """An RGB colour, each channel uniform in ``bounds`` = [lo, hi]."""
    lo, hi = bounds
    return [float(c) for c in rng.uniform(lo, hi, 3)]


def random_texture(rng: np.random.Generator, rnd: Mapping) -> dict:
    """A checkerboard (chance ``checker_probability``) or a tinted value-noise bitmap, generated on the fly;
    ``rnd`` is ``dataset.randomize`` (or a block with the same texture keys)."""
    if rng.random() < float(rnd["checker_probability"]):
        scale = draw_uniform(rng, rnd["checker_scale"])
        return {
            "type": "checkerboard",
            "color0": {"type": "rgb", "value": draw_color(rng, rnd["color"])},
            "color1": {"type": "rgb", "value": draw_color(rng, rnd["color"])},
            "to_uv": mi.ScalarTransform4f().scale([scale, scale, 1.0]),
        }
    noise = value_noise(
        rng,
        int(rnd["texture_res"]),
        int(rnd["noise_octaves"]),
        int(rnd["noise_base_cells"]),
        float(rnd["noise_persistence"]),
    )[..., None]
    a, b = np.array(draw_color(rng, rnd["color"])), np.array(draw_color(rng, rnd["color"]))
    pixels = (a * (1 - noise) + b * noise).astype(np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(pixels), "raw": False}


def random_material(rng: np.random.Generator, rnd: Mapping) -> dict:
    """One of diffuse (plain or textured), rough conductor, rough dielectric or rough plastic."""
    kind = rng.choice(list(rnd["materials"]))
    alpha = draw_uniform(rng, rnd["roughness"])
    if rng.random() < float(rnd["textured_probability"]):
        reflectance = random_texture(rng, rnd)
    else:
        reflectance = {"type": "rgb", "value": draw_color(rng, rnd["color"])}
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": reflectance}
    if kind == "conductor":
        return {
            "type": "roughconductor",
            "material": str(rng.choice(list(rnd["conductors"]))),
            "alpha": alpha,
        }
    if kind == "dielectric":
        return {"type": "roughdielectric", "alpha": alpha, "int_ior": draw_uniform(rng, rnd["ior"])}
    if kind == "plastic":
        return {"type": "roughplastic", "alpha": alpha, "diffuse_reflectance": reflectance}
    raise ConfigError(
        f"dataset.randomize.materials: unknown material '{kind}'; expected one of "
        "diffuse, conductor, dielectric, plastic"
    )


def scatter_objects(rng: np.random.Generator, rnd: Mapping, layout: Mapping) -> dict:
    """A few spheres and cubes (sizes ``object_size`` x ``layout.scale``) standing on ``layout.ground_y``
    within ``layout.spread`` of ``layout.centre`` along x and z."""
    centre, spread = layout["centre"], float(layout["spread"])
    ground_y, scale = float(layout["ground_y"]), float(layout["scale"])
    objs = {}
    for k in range(int(rng.integers(rnd["n_objects"][0], rnd["n_objects"][1] + 1))):
        size = draw_uniform(rng, rnd["object_size"]) * scale
        x = centre[0] + rng.uniform(-spread, spread)
        z = centre[2] + rng.uniform(-spread, spread)
        shape = "sphere" if rng.random() < float(rnd["sphere_probability"]) else "cube"
        to_world = mi.ScalarTransform4f().translate([x, ground_y + size, z])
        if shape == "cube":
            to_world = to_world.rotate(WORLD_UP, draw_uniform(rng, rnd["cube_rotation"])).scale(size)
        else:
            to_world = to_world.scale(size)
        objs[f"object_{k}"] = {"type": shape, "to_world": to_world, "bsdf": random_material(rng, rnd)}
    return objs


def _camera(rng: np.random.Generator, rnd: Mapping, origin, target) -> dict:
    return {
        "type": "perspective",
        "fov": draw_uniform(rng, rnd["fov"]),
        "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=target, up=WORLD_UP),
    }


def _orbit(rng: np.random.Generator, rnd: Mapping, target, distance: float) -> list[float]:
    """A camera position on a sphere around ``target`` at a random azimuth and elevation."""
    azimuth = np.radians(draw_uniform(rng, rnd["azimuth"]))
    elevation = np.radians(draw_uniform(rng, rnd["elevation"]))
    d = distance * draw_uniform(rng, rnd["camera_distance"])
    return [
        float(target[0] + d * np.cos(elevation) * np.sin(azimuth)),
        float(target[1] + d * np.sin(elevation)),
        float(target[2] + d * np.cos(elevation) * np.cos(azimuth)),
    ]


def cornell(rng: np.random.Generator, rnd: Mapping, base: Mapping) -> dict:
    """Mitsuba's Cornell box with its boxes replaced by random objects, a jittered camera and light."""
    scene = mi.cornell_box()
    for key in ("integrator", "small-box", "large-box"):
        scene.pop(key)
    scale = draw_uniform(rng, rnd["light_scale"])
    emitter = scene["light"]["emitter"]
    emitter["radiance"]["value"] = [v * scale for v in emitter["radiance"]["value"]]
    scene.update(scatter_objects(rng, rnd, base["objects"]))
    cam = base["camera"]
    d = float(cam["distance"]) * draw_uniform(rng, rnd["camera_distance"])
    origin = [rng.uniform(*cam["origin_x"]), rng.uniform(*cam["origin_y"]), d]
    target = [rng.uniform(*cam["target_x"]), rng.uniform(*cam["target_y"]), float(cam["target_z"])]
    scene["sensor"] = _camera(rng, rnd, origin, target)
    return scene


def sky_envmap(rng: np.random.Generator, rnd: Mapping) -> np.ndarray:
    """A latitude-longitude HDR sky: horizon-to-zenith gradient plus a bright sun disc."""
    h = int(rnd["env_res"])
    w = 2 * h  # latitude-longitude layout: 360 degrees of azimuth over 180 of polar angle
    theta = (np.arange(h) + 0.5) / h * np.pi  # polar angle from +Y
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    t = np.clip(np.cos(theta), 0, 1)[:, None, None]
    zenith, horizon = (
        np.array(draw_color(rng, rnd["sky_zenith"])),
        np.array(draw_color(rng, rnd["sky_horizon"])),
    )
    ground = np.array(draw_color(rng, rnd["sky_ground"]))
    sky = np.where(np.cos(theta)[:, None, None] > 0, horizon * (1 - t) + zenith * t, ground)
    sky = np.broadcast_to(sky, (h, w, 3)).copy()
    sun_theta = np.radians(draw_uniform(rng, rnd["sun_elevation"]))
    # The sun sits at azimuth 0 of the map; `env_rotation` turns the whole sky, so its azimuth varies there.
    sun_dir = np.array([np.sin(sun_theta), np.cos(sun_theta), 0.0])
    dirs = np.stack(
        [
            np.sin(theta)[:, None] * np.cos(phi),
            np.repeat(np.cos(theta)[:, None], w, 1),
            np.sin(theta)[:, None] * np.sin(phi),
        ],
        -1,
    )
    sun = dirs @ sun_dir > np.cos(np.radians(rnd["sun_radius_deg"]))
    sky[sun] = draw_uniform(rng, rnd["sun_intensity"])
    return (sky * draw_uniform(rng, rnd["light_scale"])).astype(np.float32)


def _env(rng: np.random.Generator, rnd: Mapping) -> dict:
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(sky_envmap(rng, rnd)),
        "to_world": mi.ScalarTransform4f().rotate(WORLD_UP, draw_uniform(rng, rnd["env_rotation"])),
    }


def textured_ground(rng: np.random.Generator, rnd: Mapping, plane: Mapping) -> dict:
    """A textured square of half-width ``plane.size`` lying flat at height ``plane.y``."""
    size, y = float(plane["size"]), float(plane["y"])
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f().translate([0, y, 0]).rotate(*FLOOR_ROTATION).scale(size),
        "bsdf": {"type": "diffuse", "reflectance": random_texture(rng, rnd)},
    }


def _orbit_sensor(rng: np.random.Generator, rnd: Mapping, cam: Mapping) -> dict:
    """A camera orbiting a target at height ``cam.target_height``, jittered by ``cam.target_jitter`` in x
    and z, at ``cam.distance`` (times ``camera_distance``)."""
    jitter = float(cam["target_jitter"])
    target = [rng.uniform(-jitter, jitter), float(cam["target_height"]), rng.uniform(-jitter, jitter)]
    return _camera(rng, rnd, _orbit(rng, rnd, target, float(cam["distance"])), target)


def tabletop(rng: np.random.Generator, rnd: Mapping, base: Mapping) -> dict:
    """A textured table top with a still life, lit by an area light and a dim rotated sky."""
    scene = {"type": "scene", "table": textured_ground(rng, rnd, base["table"])}
    scene.update(scatter_objects(rng, rnd, base["objects"]))
    light = base["light"]
    target = list(light["target"])
    light_pos = _orbit(rng, {**rnd, "elevation": light["elevation"]}, target, float(light["distance"]))
    scene["light"] = {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f()
        .look_at(origin=light_pos, target=target, up=WORLD_UP)
        .scale(float(light["size"])),
        "emitter": {
            "type": "area",
            "radiance": {
                "type": "rgb",
                "value": [float(light["radiance"]) * draw_uniform(rng, rnd["light_scale"])] * 3,
            },
        },
    }
    env = _env(rng, rnd)
    env["scale"] = float(base["sky_scale"])
    scene["sky"] = env
    scene["sensor"] = _orbit_sensor(rng, rnd, base["camera"])
    return scene


def outdoor(rng: np.random.Generator, rnd: Mapping, base: Mapping) -> dict:
    """An open scene on a textured ground plane lit only by a rotated HDR sky with a sun."""
    scene = {"type": "scene", "ground": textured_ground(rng, rnd, base["ground"]), "sky": _env(rng, rnd)}
    scene.update(scatter_objects(rng, rnd, base["objects"]))
    scene["sensor"] = _orbit_sensor(rng, rnd, base["camera"])
    return scene


#: Base scene builders: builder(rng, dataset.randomize, dataset.base_scenes.<base>) -> Mitsuba scene dict.
BASE_SCENES: dict[str, Callable[[np.random.Generator, Mapping, Mapping], dict]] = {
    "cornell": cornell,
    "tabletop": tabletop,
    "outdoor": outdoor,
}


def base_constants(base: str, ds: Mapping, known: Mapping) -> Mapping:
    """``dataset.base_scenes.<base>`` of a base scene among ``known`` (a family's builders); a one-line
    ConfigError for an unknown base or missing constants."""
    if base not in known:
        raise ConfigError(f"dataset.bases: unknown base scene '{base}'; expected one of {sorted(known)}")
    constants = (ds.get("base_scenes") or {}).get(base)
    if constants is None:
        raise ConfigError(f"dataset.base_scenes.{base} is missing; base scene '{base}' needs its constants")
    return constants


def build_procedural_scene(base: str, seed: int, ds: Mapping) -> dict:
    """The scene dict of base scene ``base`` permuted by ``seed`` (same seed, same scene), from the
    dataset config ``ds``: its ``randomize`` ranges and its ``base_scenes.<base>`` constants."""
    constants = base_constants(base, ds, BASE_SCENES)
    return BASE_SCENES[base](np.random.default_rng(seed), ds["randomize"], constants)
