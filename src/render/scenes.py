"""A procedural scene family for the denoising dataset, in the spirit of the KPCN set.

Bako et al. permuted 8 base scenes into ~1500 by varying camera, materials and lighting. Here a few
base scenes are built with ``mi.load_dict`` and permuted by a seed: camera position, target and
field of view, material type and roughness (diffuse, rough conductor, rough dielectric, plastic),
procedural textures (checkerboard / multi-octave value noise bitmaps made on the fly), light
intensity and environment-map rotation. All ranges come from ``dataset.randomize`` in ``conf/``.

Builders return a scene dict *without* integrator and film size: the dataset renderer adds the
AOV integrator and a box-filtered film, so user scene files go through exactly the same path.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import mitsuba as mi
import numpy as np

from src.errors import ConfigError

CONDUCTORS = ("Au", "Cu", "Al", "Ag", "Cr")


def _uniform(rng: np.random.Generator, bounds) -> float:
    lo, hi = bounds
    return float(rng.uniform(lo, hi))


def value_noise(rng: np.random.Generator, res: int, octaves: int) -> np.ndarray:
    """(res, res) fractal value noise in [0, 1]: bilinearly upsampled random lattices, halved per octave."""
    out = np.zeros((res, res))
    coords = np.linspace(0.0, 1.0, res)
    for o in range(octaves):
        cells = 2 ** (o + 2)
        lattice = rng.random((cells + 1, cells + 1))
        x = coords * cells
        i = np.minimum(x.astype(int), cells - 1)
        f = x - i
        rows = lattice[i] * (1 - f)[:, None] + lattice[i + 1] * f[:, None]  # interpolate along y
        out += (rows[:, i] * (1 - f) + rows[:, i + 1] * f) * 0.5**o  # then along x
    return (out - out.min()) / max(out.max() - out.min(), 1e-12)


def _color(rng: np.random.Generator, lo: float = 0.05, hi: float = 0.9) -> list[float]:
    return [float(c) for c in rng.uniform(lo, hi, 3)]


def random_texture(rng: np.random.Generator, rnd: Mapping) -> dict:
    """A checkerboard or a tinted value-noise bitmap, generated on the fly."""
    if rng.random() < 0.5:
        scale = _uniform(rng, rnd["checker_scale"])
        return {
            "type": "checkerboard",
            "color0": {"type": "rgb", "value": _color(rng)},
            "color1": {"type": "rgb", "value": _color(rng)},
            "to_uv": mi.ScalarTransform4f().scale([scale, scale, 1.0]),
        }
    noise = value_noise(rng, int(rnd["texture_res"]), int(rnd["noise_octaves"]))[..., None]
    a, b = np.array(_color(rng)), np.array(_color(rng))
    pixels = (a * (1 - noise) + b * noise).astype(np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(pixels), "raw": False}


def random_material(rng: np.random.Generator, rnd: Mapping) -> dict:
    """One of diffuse (plain or textured), rough conductor, rough dielectric or rough plastic."""
    kind = rng.choice(list(rnd["materials"]))
    alpha = _uniform(rng, rnd["roughness"])
    reflectance = random_texture(rng, rnd) if rng.random() < 0.5 else {"type": "rgb", "value": _color(rng)}
    if kind == "diffuse":
        return {"type": "diffuse", "reflectance": reflectance}
    if kind == "conductor":
        return {"type": "roughconductor", "material": str(rng.choice(CONDUCTORS)), "alpha": alpha}
    if kind == "dielectric":
        return {"type": "roughdielectric", "alpha": alpha, "int_ior": _uniform(rng, rnd["ior"])}
    if kind == "plastic":
        return {"type": "roughplastic", "alpha": alpha, "diffuse_reflectance": reflectance}
    raise ConfigError(
        f"dataset.randomize.materials: unknown material '{kind}'; expected one of "
        "diffuse, conductor, dielectric, plastic"
    )


def _objects(
    rng: np.random.Generator, rnd: Mapping, centre, spread: float, ground_y: float, scale: float
) -> dict:
    """A few spheres and cubes (sizes ``object_size`` x ``scale``) on the ground around ``centre``."""
    objs = {}
    for k in range(int(rng.integers(rnd["n_objects"][0], rnd["n_objects"][1] + 1))):
        size = _uniform(rng, rnd["object_size"]) * scale
        x = centre[0] + rng.uniform(-spread, spread)
        z = centre[2] + rng.uniform(-spread, spread)
        shape = "sphere" if rng.random() < 0.5 else "cube"
        to_world = mi.ScalarTransform4f().translate([x, ground_y + size, z])
        if shape == "cube":
            to_world = to_world.rotate([0, 1, 0], float(rng.uniform(0, 90))).scale(size)
        else:
            to_world = to_world.scale(size)
        objs[f"object_{k}"] = {"type": shape, "to_world": to_world, "bsdf": random_material(rng, rnd)}
    return objs


def _camera(rng: np.random.Generator, rnd: Mapping, origin, target) -> dict:
    return {
        "type": "perspective",
        "fov": _uniform(rng, rnd["fov"]),
        "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=target, up=[0, 1, 0]),
    }


def _orbit(rng: np.random.Generator, rnd: Mapping, target, distance: float) -> list[float]:
    """A camera position on a sphere around ``target`` at a random azimuth and elevation."""
    azimuth = np.radians(rng.uniform(0, 360))
    elevation = np.radians(_uniform(rng, rnd["elevation"]))
    d = distance * _uniform(rng, rnd["camera_distance"])
    return [
        float(target[0] + d * np.cos(elevation) * np.sin(azimuth)),
        float(target[1] + d * np.sin(elevation)),
        float(target[2] + d * np.cos(elevation) * np.cos(azimuth)),
    ]


def cornell(rng: np.random.Generator, rnd: Mapping) -> dict:
    """Mitsuba's Cornell box with its boxes replaced by random objects, a jittered camera and light."""
    scene = mi.cornell_box()
    for key in ("integrator", "small-box", "large-box"):
        scene.pop(key)
    scale = _uniform(rng, rnd["light_scale"])
    emitter = scene["light"]["emitter"]
    emitter["radiance"]["value"] = [v * scale for v in emitter["radiance"]["value"]]
    scene.update(_objects(rng, rnd, centre=(0.0, 0.0, 0.0), spread=0.55, ground_y=-1.0, scale=1.0))
    d = 3.9 * _uniform(rng, rnd["camera_distance"])
    origin = [rng.uniform(-0.4, 0.4), rng.uniform(-0.3, 0.4), d]
    target = [rng.uniform(-0.2, 0.2), rng.uniform(-0.4, 0.1), 0.0]
    scene["sensor"] = _camera(rng, rnd, origin, target)
    return scene


def sky_envmap(rng: np.random.Generator, rnd: Mapping) -> np.ndarray:
    """A latitude-longitude HDR sky: horizon-to-zenith gradient plus a bright sun disc."""
    h = int(rnd["env_res"])
    w = 2 * h
    theta = (np.arange(h) + 0.5) / h * np.pi  # polar angle from +Y
    phi = (np.arange(w) + 0.5) / w * 2 * np.pi
    t = np.clip(np.cos(theta), 0, 1)[:, None, None]
    zenith, horizon = np.array(_color(rng, 0.1, 0.6)), np.array(_color(rng, 0.6, 1.0))
    ground = np.array(_color(rng, 0.05, 0.25))
    sky = np.where(np.cos(theta)[:, None, None] > 0, horizon * (1 - t) + zenith * t, ground)
    sky = np.broadcast_to(sky, (h, w, 3)).copy()
    sun_theta = np.radians(_uniform(rng, rnd["sun_elevation"]))
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
    sky[sun] = _uniform(rng, rnd["sun_intensity"])
    return (sky * _uniform(rng, rnd["light_scale"])).astype(np.float32)


def _env(rng: np.random.Generator, rnd: Mapping) -> dict:
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(sky_envmap(rng, rnd)),
        "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], _uniform(rng, rnd["env_rotation"])),
    }


def _ground(rng: np.random.Generator, rnd: Mapping, size: float, y: float) -> dict:
    return {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f().translate([0, y, 0]).rotate([1, 0, 0], -90).scale(size),
        "bsdf": {"type": "diffuse", "reflectance": random_texture(rng, rnd)},
    }


def tabletop(rng: np.random.Generator, rnd: Mapping) -> dict:
    """A textured table top with a still life, lit by an area light and a dim rotated sky."""
    scene = {"type": "scene", "table": _ground(rng, rnd, 2.0, 0.0)}
    scene.update(_objects(rng, rnd, centre=(0.0, 0.0, 0.0), spread=0.6, ground_y=0.0, scale=0.8))
    light_pos = _orbit(rng, {**rnd, "elevation": [40, 75]}, (0, 0, 0), 2.5)
    scene["light"] = {
        "type": "rectangle",
        "to_world": mi.ScalarTransform4f()
        .look_at(origin=light_pos, target=[0, 0, 0], up=[0, 1, 0])
        .scale(0.4),
        "emitter": {
            "type": "area",
            "radiance": {"type": "rgb", "value": [15 * _uniform(rng, rnd["light_scale"])] * 3},
        },
    }
    env = _env(rng, rnd)
    env["scale"] = 0.2
    scene["sky"] = env
    target = [rng.uniform(-0.2, 0.2), 0.15, rng.uniform(-0.2, 0.2)]
    scene["sensor"] = _camera(rng, rnd, _orbit(rng, rnd, target, 2.6), target)
    return scene


def outdoor(rng: np.random.Generator, rnd: Mapping) -> dict:
    """An open scene on a textured ground plane lit only by a rotated HDR sky with a sun."""
    scene = {"type": "scene", "ground": _ground(rng, rnd, 6.0, 0.0), "sky": _env(rng, rnd)}
    scene.update(_objects(rng, rnd, centre=(0.0, 0.0, 0.0), spread=1.0, ground_y=0.0, scale=1.5))
    target = [rng.uniform(-0.3, 0.3), 0.3, rng.uniform(-0.3, 0.3)]
    scene["sensor"] = _camera(rng, rnd, _orbit(rng, rnd, target, 4.0), target)
    return scene


BASE_SCENES: dict[str, Callable[[np.random.Generator, Mapping], dict]] = {
    "cornell": cornell,
    "tabletop": tabletop,
    "outdoor": outdoor,
}


def build_procedural_scene(base: str, seed: int, rnd: Mapping) -> dict:
    """The scene dict of base scene ``base`` permuted by ``seed`` (same seed, same scene)."""
    if base not in BASE_SCENES:
        raise ConfigError(
            f"dataset.bases: unknown base scene '{base}'; expected one of {sorted(BASE_SCENES)}"
        )
    return BASE_SCENES[base](np.random.default_rng(seed), rnd)
