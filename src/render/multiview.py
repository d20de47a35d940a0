"""Render procedural multi-view scenes with Mitsuba and write them in the Blender (nerf_synthetic) format.

Output per scene, exactly what ``src.data.blender.load_blender_split`` (and public NeRF code) reads:

    <out>/<scene>/transforms_{train,val,test}.json   camera_angle_x + frames (file_path, transform_matrix)
    <out>/<scene>/{train,val,test}/r_<i>.png         8-bit RGBA, straight alpha, sRGB colour
    <out>/<scene>/nrbench_render.json                render key + timings (cache bookkeeping)

The camera convention is in ``multiview_cameras``, alpha and colour in ``multiview_views``, the scenes in
``multiview_scenes`` and the render key in ``multiview_cache``. A scene whose render key is unchanged is
skipped. A scene is written into a temporary sibling folder and renamed into place when complete, so an
interrupted run never leaves a half scene that looks finished.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from pathlib import Path

from PIL import Image
from tqdm import tqdm

from src.errors import ConfigError
from src.io.atomic import atomic_directory
from src.render.multiview_cache import KEY_FILE, is_current, render_key
from src.render.multiview_cameras import split_poses
from src.render.multiview_scenes import SCENE_BUILDERS, build_scene
from src.render.multiview_seeds import SPLIT_IDS, SPLITS, scene_seed
from src.render.multiview_views import encode_rgba8, make_sensor, render_view
from src.render.render_dataset import split_passes
from src.render.stale_renders import remove_stale_scenes


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

    Scenes whose render key is unchanged are skipped; scene folders we rendered that ``dataset.scenes``
    no longer lists are deleted (``remove_stale_scenes``: a user's own scene folders stay). Returns
    counts, render seconds (``mi.render`` only) and throughput in camera rays (pixel samples) per second.
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
    removed = remove_stale_scenes(out_dir, KEY_FILE, names)
    keys = {name: render_key(ds, name) for name in names}
    todo = [name for name in names if not is_current(out_dir / name, keys[name])]
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
        "scenes_removed": len(removed),
        "views_rendered": sum(s["views"] for s in per_scene.values()),
        "rays": rays,
        "render_seconds": round(seconds, 3),
        "rays_per_second": rays / seconds if seconds > 0 else None,
        "per_scene": {
            n: {**s, "rays_per_second": s["rays"] / s["seconds"] if s["seconds"] > 0 else None}
            for n, s in per_scene.items()
        },
    }
