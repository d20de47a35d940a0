"""Render procedural multi-view scenes with Mitsuba and write them in the Blender (nerf_synthetic) format.

Output per scene, exactly what ``src.data.blender.load_blender_split`` (and public NeRF code) reads:

    <out>/<scene>/transforms_{train,val,test}.json   camera_angle_x + frames (file_path, transform_matrix)
    <out>/<scene>/{train,val,test}/r_<i>.png         8-bit RGBA, straight alpha, sRGB colour
    <out>/<scene>/nrbench_render.json                render key + timings (cache bookkeeping)

Conventions:
- World: +z up, like Blender. Cameras sit at distance ``radius`` from the origin and look at it; train
  and val positions are uniform (by area) on the spherical zone between ``elevation_range_deg``, test
  views follow a circle at ``test_elevation_deg`` (evenly spaced azimuths), like the original scenes.
- ``transform_matrix`` is the OpenGL camera-to-world: columns are the camera's right (+x), up (+y) and
  back (+z; the camera looks down -z) axes and its position. Mitsuba's ``look_at`` frame has columns
  (left, up, forward), its image x growing towards -left: Mitsuba's to_world = c2w @ diag(-1, 1, -1, 1).
  Both the Mitsuba sensor and the JSON are made from the one c2w, so they cannot disagree.
- Alpha: Mitsuba's path integrator marks a sample valid (alpha 1) when it hits geometry *or* sees a
  visible environment emitter; with ``hide_emitters`` the environment still lights the scene but
  camera rays that miss all geometry get alpha 0 (a transparent background, as Blender's film).
- Colour: the film's RGB is premultiplied by coverage (misses contribute 0); PNGs store straight colour
  rgb / alpha, clipped to [0, 1], sRGB OETF, round(255 x); alpha round(255 a). The ``box`` pixel filter
  (``rfilter``) makes each pixel the average over its own square, the pixel model of NeRF/mip-NeRF.

Caching: a scene is skipped when its render key (scene, every config value that changes its pixels,
per-split seeds, ``FORMAT_VERSION``) equals the one stored in its ``nrbench_render.json``. A scene is
written into a temporary sibling folder and renamed into place when complete, so an interrupted run
never leaves a half scene that looks finished.
"""

from __future__ import annotations

import hashlib
import json
import math
import time
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from PIL import Image
from tqdm import tqdm

from src.errors import ConfigError
from src.io.atomic import atomic_directory
from src.render.render_dataset import split_passes

SPLITS = ("train", "val", "test")
SPLIT_IDS = {"train": 1, "val": 2, "test": 3}
#: The cache bookkeeping file inside each scene folder.
KEY_FILE = "nrbench_render.json"
#: Bump when the renderer's output changes for the same config (invalidates every cached scene).
FORMAT_VERSION = 1
#: Dataset keys that do not change any rendered pixel (kept out of the render key).
NON_PIXEL_KEYS = frozenset({"name", "scenes", "near", "far", "background", "scene_params", "root"})
#: Camera ``up`` hint of the world (+z, Blender's convention), and the fallback when looking along it.
WORLD_UP = np.array([0.0, 0.0, 1.0])
FALLBACK_UP = np.array([0.0, 1.0, 0.0])
#: Mitsuba's envmap is +y up; this rotation (about +x by 90 degrees) maps its +y onto the world's +z.
ENVMAP_UP_ROTATION = ([1.0, 0.0, 0.0], 90.0)
#: OpenGL camera axes (right, up, back) -> Mitsuba camera axes (left, up, forward).
GL_TO_MITSUBA = np.diag([-1.0, 1.0, -1.0, 1.0])


# ---------------------------------------------------------------------------------------------- cameras


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


def scene_seed(seed: int, scene: str, *extra: int) -> int:
    """A 32-bit seed unique to (dataset seed, scene name, extra integers...)."""
    return int(np.random.SeedSequence([int(seed), zlib.crc32(scene.encode()), *extra]).generate_state(1)[0])


def split_seed(seed: int, scene: str, split: str) -> int:
    """The seed of the camera poses of one split of one scene."""
    return scene_seed(seed, scene, SPLIT_IDS[split])


def split_poses(ds: Mapping, scene: str, split: str) -> np.ndarray:
    """(views, 4, 4) OpenGL camera-to-world matrices of ``split``: random on the zone, or the test circle."""
    n = int(ds["views"][split])
    if split == "test":
        return circle_poses(n, float(ds["radius"]), ds["test_elevation_deg"], ds["test_azimuth_start_deg"])
    rng = np.random.default_rng(split_seed(int(ds["seed"]), scene, split))
    return hemisphere_poses(rng, n, float(ds["radius"]), ds["elevation_range_deg"])


# ----------------------------------------------------------------------------------------------- scenes


def _transform(matrix=None):
    import mitsuba as mi

    return mi.ScalarTransform4f() if matrix is None else mi.ScalarTransform4f(np.asarray(matrix).tolist())


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


def _envmap_emitter(env: Mapping) -> dict:
    import mitsuba as mi

    axis, angle = ENVMAP_UP_ROTATION
    return {
        "type": "envmap",
        "bitmap": mi.Bitmap(studio_envmap(env)),
        "to_world": mi.ScalarTransform4f().rotate([0, 0, 1], float(env["rotation_deg"])).rotate(axis, angle),
    }


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
        f"dataset.scene_params.materials.rows: unknown material '{kind}'; expected conductor, plastic or "
        "dielectric"
    )


def materials_scene(rng: np.random.Generator, p: Mapping, ds: Mapping) -> dict:
    """A grid of spheres in the z = 0 plane: one material kind per row (``rows``), GGX roughness graded
    along the columns (``roughness``), under the structured ``env`` map. No ground plane."""
    rows, alphas = list(p["rows"]), [float(a) for a in p["roughness"]]
    spacing, radius = float(p["spacing"]), float(p["sphere_radius"])
    scene: dict = {"type": "scene", "env": _envmap_emitter(p["env"])}
    for r, kind in enumerate(rows):
        for c, alpha in enumerate(alphas):
            centre = [(c - (len(alphas) - 1) / 2) * spacing, ((len(rows) - 1) / 2 - r) * spacing, 0.0]
            _check_inside(ds, "materials", np.linalg.norm(centre) + radius)
            scene[f"sphere_{r}_{c}"] = {
                "type": "sphere",
                "center": centre,
                "radius": radius,
                "bsdf": _material(kind, alpha, p),
            }
    return scene


def _random_rotation(rng: np.random.Generator):
    import mitsuba as mi

    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    return mi.ScalarTransform4f().rotate(axis.tolist(), float(rng.uniform(0.0, 360.0)))


def _textured_diffuse(rng: np.random.Generator, p: Mapping) -> dict:
    from src.render.scenes import _color, random_texture

    if rng.random() < float(p["textured_fraction"]):
        reflectance = random_texture(rng, p)  # checkerboard or value-noise bitmap, 50/50
    else:
        reflectance = {"type": "rgb", "value": _color(rng)}
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
        extent = size * {"sphere": 1.0, "cube": math.sqrt(3.0), "cylinder": math.sqrt(2.0)}[shape]
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


#: Procedural multi-view scenes: builder(rng, dataset.scene_params.<name>, dataset) -> Mitsuba scene dict
#: (no integrator, no sensor). Tests may register extra builders here.
SCENE_BUILDERS: dict[str, Callable[[np.random.Generator, Mapping, Mapping], dict]] = {
    "materials": materials_scene,
    "busy": busy_scene,
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


# ------------------------------------------------------------------------------------------- rendering


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


def srgb_oetf(linear: np.ndarray) -> np.ndarray:
    """sRGB transfer function (IEC 61966-2-1) of linear values in [0, 1]."""
    linear = np.asarray(linear)
    return np.where(
        linear <= 0.0031308, 12.92 * linear, 1.055 * np.power(np.maximum(linear, 0.0031308), 1 / 2.4) - 0.055
    )


def encode_rgba8(rgba: np.ndarray) -> np.ndarray:
    """Premultiplied linear RGBA (H, W, 4) -> uint8 straight-alpha sRGB RGBA (H, W, 4), as Blender's PNGs."""
    alpha = np.clip(rgba[..., 3:], 0.0, 1.0)
    straight = np.divide(rgba[..., :3], alpha, out=np.zeros_like(rgba[..., :3]), where=alpha > 0)
    colour = srgb_oetf(np.clip(straight, 0.0, 1.0))
    return np.round(np.concatenate([colour, alpha], axis=-1) * 255.0).astype(np.uint8)


def render_key(ds: Mapping, scene: str) -> str:
    """Hash of everything that decides the pixels and poses of ``scene``: the renderer version, the
    scene's parameters, every dataset value outside ``NON_PIXEL_KEYS`` and the per-split pose seeds."""
    payload = {
        "format_version": FORMAT_VERSION,
        "scene": scene,
        "scene_params": (ds.get("scene_params") or {}).get(scene),
        "split_seeds": {s: split_seed(int(ds["seed"]), scene, s) for s in SPLITS},
        **{k: v for k, v in ds.items() if k not in NON_PIXEL_KEYS},
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def validate_config(ds: Mapping) -> None:
    """One-line ConfigErrors for values the renderer cannot honour."""
    for key in ("width", "height", "spp", "max_pass_samples"):
        if int(ds[key]) < 1:
            raise ConfigError(f"dataset.{key}={ds[key]}: expected an integer >= 1")
    for split in SPLITS:
        if split not in ds["views"] or int(ds["views"][split]) < 1:
            raise ConfigError(
                f"dataset.views.{split}: expected a view count >= 1, got {ds['views'].get(split)}"
            )
    if not 0.0 < float(ds["camera_angle_x"]) < math.pi:
        raise ConfigError(f"dataset.camera_angle_x={ds['camera_angle_x']}: expected radians in (0, pi)")
    radius, bound = float(ds["radius"]), float(ds["bound_radius"])
    near, far = float(ds["near"]), float(ds["far"])
    if not near <= radius - bound or not radius + bound <= far:
        raise ConfigError(
            f"dataset: near={near} / far={far} do not contain the scene ball (radius {bound}) seen from "
            f"radius={radius}; expected near <= {radius - bound:g} and far >= {radius + bound:g}"
        )


def _read_key(scene_dir: Path) -> str | None:
    try:
        return json.loads((scene_dir / KEY_FILE).read_text())["render_key"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def _is_current(scene_dir: Path, key: str) -> bool:
    files = [scene_dir / f"transforms_{s}.json" for s in SPLITS]
    return _read_key(scene_dir) == key and all(f.is_file() for f in files)


def render_scene(ds: Mapping, name: str, tmp_dir: Path, progress: tqdm | None = None) -> dict:
    """Render every split of scene ``name`` into ``tmp_dir``; returns views, rays and seconds."""
    import mitsuba as mi

    scene = mi.load_dict(build_scene(name, ds))
    width, height, spp = int(ds["width"]), int(ds["height"]), int(ds["spp"])
    passes = split_passes(spp, width * height, int(ds["max_pass_samples"]))
    seconds, views = 0.0, 0
    for split in SPLITS:
        poses = split_poses(ds, name, split)
        (tmp_dir / split).mkdir()
        frames = []
        for i, c2w in enumerate(poses):
            seeds = [scene_seed(int(ds["seed"]), name, SPLIT_IDS[split], i, k) for k in range(len(passes))]
            start = time.perf_counter()
            rgba = render_view(scene, make_sensor(ds, c2w), spp, seeds, passes)
            seconds += time.perf_counter() - start
            Image.fromarray(encode_rgba8(rgba), mode="RGBA").save(tmp_dir / split / f"r_{i}.png")
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
            views += 1
            if progress is not None:
                progress.update(1)
        meta = {"camera_angle_x": float(ds["camera_angle_x"]), "frames": frames}
        (tmp_dir / f"transforms_{split}.json").write_text(json.dumps(meta, indent=4) + "\n")
    rays = views * width * height * spp
    return {"views": views, "rays": rays, "seconds": seconds}


def render_multiview_dataset(ds: Mapping, out_dir: Path, variant: str = "auto") -> dict:
    """Render every scene of ``ds['scenes']`` into ``out_dir/<scene>`` in the Blender format.

    Scenes whose render key is unchanged are skipped. Returns counts, render seconds (``mi.render``
    only) and throughput in camera rays (pixel samples) per second.
    """
    from src.render.backend import set_mitsuba_variant

    validate_config(ds)
    names = list(ds["scenes"])
    if len(set(names)) != len(names):
        raise ConfigError(f"dataset.scenes: names are not unique: {names}")
    for name in names:
        if name not in SCENE_BUILDERS:
            raise ConfigError(
                f"dataset.scenes: unknown scene '{name}'; expected one of {sorted(SCENE_BUILDERS)}"
            )
    variant = set_mitsuba_variant(variant)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    keys = {name: render_key(ds, name) for name in names}
    todo = [name for name in names if not _is_current(out_dir / name, keys[name])]
    per_view = sum(int(ds["views"][s]) for s in SPLITS)
    per_scene: dict[str, dict] = {}
    with tqdm(total=per_view * len(todo), desc=f"multiview [{variant}]", unit="view") as progress:
        for name in todo:
            progress.set_postfix_str(name)
            with atomic_directory(out_dir / name) as tmp:
                stats = render_scene(ds, name, tmp, progress)
                record = {"render_key": keys[name], "variant": variant, **stats}
                (tmp / KEY_FILE).write_text(json.dumps(record, indent=1) + "\n")
            per_scene[name] = stats
    rays = sum(s["rays"] for s in per_scene.values())
    seconds = sum(s["seconds"] for s in per_scene.values())
    return {
        "variant": variant,
        "scenes": len(names),
        "scenes_rendered": len(todo),
        "scenes_cached": len(names) - len(todo),
        "views_rendered": sum(s["views"] for s in per_scene.values()),
        "rays": rays,
        "render_seconds": round(seconds, 3),
        "rays_per_second": rays / seconds if seconds > 0 else None,
        "per_scene": {
            n: {**s, "rays_per_second": s["rays"] / s["seconds"] if s["seconds"] > 0 else None}
            for n, s in per_scene.items()
        },
    }
