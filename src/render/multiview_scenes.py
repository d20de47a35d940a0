"""The procedural multi-view scenes as Mitsuba scene dicts: ``spheres`` (a grid of spheres, one material
per row, graded roughness), ``busy`` (many small textured objects) and ``tabletop`` (glossy spheres and
textured objects on a textured disk), and the path integrator they use."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping

import numpy as np

from src.errors import ConfigError
from src.render.multiview_seeds import scene_seed
from src.render.studio_envmap import envmap_emitter

#: Distance from a busy object's centre to its farthest point, per unit ``size`` (geometry, not a parameter):
#: sphere radius 1, cube half-edge 1 (half-diagonal sqrt 3), cylinder radius 1 and half-length 1 (sqrt 2).
BOUNDING_RADIUS = {"sphere": 1.0, "cube": math.sqrt(3.0), "cylinder": math.sqrt(2.0)}


def _material(kind: str, roughness: float, p: Mapping) -> dict:
    if kind == "conductor":
        return {"type": "roughconductor", "material": str(p["conductor"]), "alpha": roughness}
    if kind == "plastic":
        return {
            "type": "roughplastic",
            "alpha": roughness,
            "diffuse_reflectance": {"type": "rgb", "value": list(p["plastic_color"])},
        }
    if kind == "dielectric":
        return {"type": "roughdielectric", "alpha": roughness, "int_ior": float(p["dielectric_ior"])}
    raise ConfigError(
        f"dataset.scene_params.spheres.rows: unknown material '{kind}'; expected conductor, plastic or "
        "dielectric"
    )


def spheres_scene(rng: np.random.Generator, p: Mapping, ds: Mapping) -> dict:
    """A grid of spheres in the z = 0 plane: one material kind per row (``rows``), GGX roughness graded
    along the columns (``roughness``), under the structured ``env`` map. No ground plane."""
    rows, alphas = list(p["rows"]), [float(a) for a in p["roughness"]]
    spacing, radius = float(p["spacing"]), float(p["sphere_radius"])
    scene: dict = {"type": "scene", "env": envmap_emitter(p["env"])}
    for r, kind in enumerate(rows):
        for c, alpha in enumerate(alphas):
            centre = [(c - (len(alphas) - 1) / 2) * spacing, ((len(rows) - 1) / 2 - r) * spacing, 0.0]
            _check_inside(ds, "spheres", np.linalg.norm(centre) + radius)
            scene[f"sphere_{r}_{c}"] = {
                "type": "sphere",
                "center": centre,
                "radius": radius,
                "bsdf": _material(kind, alpha, p),
            }
    return scene


def _random_rotation(rng: np.random.Generator):
    """A rotation by an angle uniform in the full turn [0, 360) degrees about a uniformly random axis
    (the bounds are the whole circle, not a parameter)."""
    import mitsuba as mi

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return mi.ScalarTransform4f().rotate(axis.tolist(), float(rng.uniform(0.0, 360.0)))


def _textured_diffuse(rng: np.random.Generator, p: Mapping) -> dict:
    from src.render.scenes import draw_color, random_texture

    if rng.random() < float(p["textured_fraction"]):
        reflectance = random_texture(rng, p)  # checkerboard or value-noise bitmap (checker_probability)
    else:
        reflectance = {"type": "rgb", "value": draw_color(rng, p["color"])}
    return {"type": "twosided", "bsdf": {"type": "diffuse", "reflectance": reflectance}}


def busy_scene(rng: np.random.Generator, p: Mapping, ds: Mapping) -> dict:
    """``n_objects`` small spheres, boxes and capped cylinders with checkerboard / value-noise diffuse
    textures, packed inside the ``bound_radius`` ball, lit by a constant ambient environment and a
    directional light."""
    import mitsuba as mi

    bound = float(ds["bound_radius"])
    shapes = list(p["shapes"])
    unknown = sorted(set(shapes) - {"sphere", "cube", "cylinder"})
    if unknown:
        raise ConfigError(
            f"dataset.scene_params.busy.shapes: unknown {unknown}; expected sphere, cube or cylinder"
        )
    scene: dict = {
        "type": "scene",
        "ambient": {"type": "constant", "radiance": {"type": "rgb", "value": float(p["ambient"])}},
        "sun": {
            "type": "directional",
            "direction": [float(v) for v in p["sun"]["direction"]],
            "irradiance": {"type": "rgb", "value": float(p["sun"]["irradiance"])},
        },
    }
    lo, hi = (float(s) for s in p["size"])
    for k in range(int(p["n_objects"])):
        shape = str(rng.choice(shapes))
        size = float(rng.uniform(lo, hi))
        extent = size * BOUNDING_RADIUS[shape]
        if extent >= bound:
            raise ConfigError(
                f"dataset.scene_params.busy.size={[lo, hi]}: an object of extent {extent:.3g} does not "
                f"fit in dataset.bound_radius={bound}"
            )
        direction = rng.normal(size=3)
        direction /= np.linalg.norm(direction)
        centre = direction * (bound - extent) * rng.random() ** (1.0 / 3.0)  # uniform in the ball
        bsdf = _textured_diffuse(rng, p)
        base = mi.ScalarTransform4f().translate(centre.tolist()) @ _random_rotation(rng)
        if shape == "sphere":
            scene[f"object_{k}"] = {"type": "sphere", "to_world": base.scale(size), "bsdf": bsdf}
        elif shape == "cube":
            scene[f"object_{k}"] = {"type": "cube", "to_world": base.scale(size), "bsdf": bsdf}
        else:  # unit cylinder along z in [0, 1], centred, with disks (normals outwards) as caps
            body = base.scale([size, size, 2 * size])
            scene[f"object_{k}"] = {
                "type": "cylinder",
                "to_world": body.translate([0.0, 0.0, -0.5]),
                "bsdf": bsdf,
            }
            scene[f"object_{k}_top"] = {"type": "disk", "to_world": body.translate([0, 0, 0.5]), "bsdf": bsdf}
            scene[f"object_{k}_bottom"] = {
                "type": "disk",
                "to_world": body.translate([0, 0, -0.5]).rotate([1, 0, 0], 180.0),
                "bsdf": bsdf,
            }
    return scene


def tabletop_scene(rng: np.random.Generator, p: Mapping, ds: Mapping) -> dict:
    """Glossy and textured objects together, the benchmark kind of NeRF scene: a checkerboard ``ground``
    disk, ``glossy`` spheres (one per entry: material and GGX roughness) on a circle, and
    ``n_textured`` textured diffuse cubes (checkerboard or value noise, as ``busy``) between them, under
    the ``spheres`` scene's studio environment, so the reflections move with the view and the textures
    need detail."""
    import mitsuba as mi

    ground = p["ground"]
    z0, disk_radius = float(ground["height"]), float(ground["radius"])
    _check_inside(ds, "tabletop", math.hypot(z0, disk_radius))
    scene: dict = {
        "type": "scene",
        "env": envmap_emitter(p["env"]),
        "ground": {
            "type": "disk",
            "to_world": mi.ScalarTransform4f().translate([0.0, 0.0, z0]).scale(disk_radius),
            "bsdf": {
                "type": "diffuse",
                "reflectance": {
                    "type": "checkerboard",
                    "color0": {"type": "rgb", "value": list(ground["color0"])},
                    "color1": {"type": "rgb", "value": list(ground["color1"])},
                    "to_uv": mi.ScalarTransform4f().scale([ground["checks"], ground["checks"], 1.0]),
                },
            },
        },
    }
    radius, ring = float(p["sphere_radius"]), float(p["ring_radius"])
    for k, sphere in enumerate(p["glossy"]):
        angle = 2 * math.pi * k / len(p["glossy"])
        centre = [ring * math.cos(angle), ring * math.sin(angle), z0 + radius]
        _check_inside(ds, "tabletop", float(np.linalg.norm(centre)) + radius)
        scene[f"glossy_{k}"] = {
            "type": "sphere",
            "center": centre,
            "radius": radius,
            "bsdf": _material(str(sphere["material"]), float(sphere["roughness"]), p),
        }
    half = float(p["cube_half_edge"])
    for k in range(int(p["n_textured"])):
        angle = 2 * math.pi * (k + 0.5) / int(p["n_textured"])
        turn = float(rng.uniform(0.0, 90.0))  # about the up axis: the cube stays on the ground
        centre = [ring * math.cos(angle), ring * math.sin(angle), z0 + half]
        _check_inside(ds, "tabletop", float(np.linalg.norm(centre)) + half * BOUNDING_RADIUS["cube"])
        scene[f"textured_{k}"] = {
            "type": "cube",
            "to_world": mi.ScalarTransform4f().translate(centre).rotate([0, 0, 1], turn).scale(half),
            "bsdf": _textured_diffuse(rng, {**p, "textured_fraction": 1.0}),
        }
    scene["centre"] = {
        "type": "sphere",
        "center": [0.0, 0.0, z0 + float(p["centre_radius"])],
        "radius": float(p["centre_radius"]),
        "bsdf": _textured_diffuse(rng, {**p, "textured_fraction": 1.0}),
    }
    return scene


#: Procedural multi-view scenes: builder(rng, dataset.scene_params.<name>, dataset) -> Mitsuba scene dict
#: (no integrator, no sensor). Tests may register extra builders here.
SCENE_BUILDERS: dict[str, Callable[[np.random.Generator, Mapping, Mapping], dict]] = {
    "spheres": spheres_scene,
    "busy": busy_scene,
    "tabletop": tabletop_scene,
}


def _check_inside(ds: Mapping, scene: str, extent: float) -> None:
    bound = float(ds["bound_radius"])
    if extent > bound + 1e-9:
        raise ConfigError(
            f"dataset.scene_params.{scene}: objects reach {extent:.3g} from the origin; expected at most "
            f"dataset.bound_radius={bound}"
        )


def build_scene(name: str, ds: Mapping) -> dict:
    """The Mitsuba scene dict of procedural scene ``name`` (content seeded by dataset seed and name),
    with the path integrator (emitters hidden from camera rays: alpha 0 where rays miss geometry)."""
    if name not in SCENE_BUILDERS:
        raise ConfigError(f"dataset.scenes: unknown scene '{name}'; expected one of {sorted(SCENE_BUILDERS)}")
    params = (ds.get("scene_params") or {}).get(name)
    if params is None:
        raise ConfigError(f"dataset.scene_params.{name} is missing; scene '{name}' needs its parameters")
    scene = SCENE_BUILDERS[name](np.random.default_rng(scene_seed(int(ds["seed"]), name)), params, ds)
    scene["integrator"] = {
        "type": "path",
        "max_depth": int(ds["max_depth"]),
        "rr_depth": int(ds["rr_depth"]),
        "hide_emitters": True,
    }
    return scene
