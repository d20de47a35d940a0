"""Mitsuba multi-view renderer: Blender-format output, camera convention, alpha, caching (tiny renders)."""

import json
import math

import numpy as np
import pytest
import torch
from omegaconf import OmegaConf

from src.data.blender import load_blender_split
from src.data.rays import generate_rays
from src.errors import ConfigError
from src.render import multiview
from src.render.multiview import render_multiview_dataset
from src.render.multiview_cache import KEY_FILE, render_key
from src.render.multiview_cameras import (
    circle_poses,
    hemisphere_poses,
    look_at_c2w,
    mitsuba_to_world,
    split_poses,
)
from src.render.multiview_scenes import SCENE_BUILDERS
from src.render.multiview_views import encode_rgba8
from tests.conftest import CONF_DIR, one_line_error

PROBE = np.array([0.55, -0.35, 0.3])  # an off-centre point inside the scene ball


@pytest.fixture(scope="module")
def ds():
    """The shipped config at a tiny size: 24x24, 2 train / 1 val / 2 test views, few samples."""
    cfg = OmegaConf.load(f"{CONF_DIR}/dataset/nerf_procedural.yaml")
    cfg.seed = 0
    small = OmegaConf.to_container(cfg, resolve=True)
    small.update(width=24, height=24, spp=4, views={"train": 2, "val": 1, "test": 2})
    small["scene_params"]["busy"].update(n_objects=12, texture_res=16)
    small["scene_params"]["tabletop"].update(texture_res=16)
    for scene in ("spheres", "tabletop"):
        small["scene_params"][scene]["env"]["res"] = 32
    return small


def project(c2w, focal, width, height, point):
    """Continuous image coordinates (x right, y down; pixel i spans [i, i + 1)) of a world point, in the
    camera model of ``generate_rays`` (OpenGL camera, principal point at the image centre)."""
    p = np.linalg.solve(c2w, np.append(point, 1.0))[:3]
    return np.array([width / 2 + focal * p[0] / -p[2], height / 2 - focal * p[1] / -p[2]])


def test_camera_frames_match_mitsuba_look_at(mitsuba_variant):
    import mitsuba as mi

    rng = np.random.default_rng(0)
    for position in [*rng.normal(size=(5, 3)) * 3, [0.0, 0.0, 4.0], [0.0, 0.0, -4.0]]:
        c2w = look_at_c2w(position)
        np.testing.assert_allclose(c2w[:3, :3].T @ c2w[:3, :3], np.eye(3), atol=1e-12)
        assert np.linalg.det(c2w[:3, :3]) == pytest.approx(1.0)
        np.testing.assert_allclose(-c2w[:3, 2], -np.asarray(position) / np.linalg.norm(position), atol=1e-12)
        assert c2w[2, 1] >= 0  # the image's up leans towards world +z
        up = [0, 0, 1] if abs(position[0]) + abs(position[1]) > 0 else [0, 1, 0]
        ref = mi.ScalarTransform4f().look_at(origin=list(map(float, position)), target=[0, 0, 0], up=up)
        np.testing.assert_allclose(mitsuba_to_world(c2w), np.array(ref.matrix), atol=1e-5)


def test_pose_distributions():
    rng = np.random.default_rng(1)
    poses = hemisphere_poses(rng, 2000, 4.0, [0.0, 90.0])
    z = poses[:, 2, 3] / 4.0
    np.testing.assert_allclose(np.linalg.norm(poses[:, :3, 3], axis=1), 4.0)
    assert z.min() >= 0 and abs(z.mean() - 0.5) < 0.03  # uniform by area: z ~ U(0, 1)
    circle = circle_poses(8, 4.0, 30.0, 0.0)
    np.testing.assert_allclose(circle[:, 2, 3], 4.0 * math.sin(math.radians(30)))
    np.testing.assert_allclose(circle[0, :3, 3], [4 * math.cos(math.radians(30)), 0, 2], atol=1e-12)
    with pytest.raises(ConfigError, match="elevation_range_deg"):
        hemisphere_poses(rng, 2, 4.0, [50.0, 10.0])


def test_encode_rgba8_unpremultiplies_and_srgb_encodes():
    rgba = np.array([[[0.25, 0.0, 2.0, 0.5], [0.0, 0.0, 0.0, 0.0], [0.001, 0.5, 1.0, 1.0]]], np.float32)
    out = encode_rgba8(rgba)
    srgb_half = 1.055 * 0.5 ** (1 / 2.4) - 0.055
    np.testing.assert_array_equal(out[0, 0], [round(255 * srgb_half), 0, 255, 128])
    np.testing.assert_array_equal(out[0, 1], [0, 0, 0, 0])
    np.testing.assert_array_equal(out[0, 2], [round(255 * 12.92 * 0.001), round(255 * srgb_half), 255, 255])


def test_render_key_tracks_pixels_only(ds):
    key = render_key(ds, "busy")
    assert key == render_key(dict(ds), "busy") != render_key(ds, "spheres")
    assert render_key({**ds, "near": 1.0, "far": 9.0, "background": [0, 0, 0]}, "busy") == key
    assert render_key({**ds, "spp": 8}, "busy") != key
    assert render_key({**ds, "seed": 1}, "busy") != key
    other = {**ds["scene_params"], "busy": {**ds["scene_params"]["busy"], "n_objects": 5}}
    assert render_key({**ds, "scene_params": other}, "busy") != key
    assert render_key({**ds, "scene_params": other}, "spheres") == render_key(ds, "spheres")


def test_config_errors_are_one_line(ds, tmp_path):
    with pytest.raises(ConfigError) as err:
        render_multiview_dataset({**ds, "near": 3.0}, tmp_path)
    one_line_error(err, "near=3.0", "far=6.0", "expected near <= 2.7")
    with pytest.raises(ConfigError) as err:
        render_multiview_dataset({**ds, "scenes": ["lego"]}, tmp_path)
    one_line_error(err, "dataset.scenes", "lego", "busy")
    with pytest.raises(ConfigError) as err:
        render_multiview_dataset({**ds, "views": {"train": 2, "val": 0, "test": 1}}, tmp_path)
    one_line_error(err, "dataset.views.val")
    crowded = {**ds["scene_params"], "spheres": {**ds["scene_params"]["spheres"], "spacing": 1.0}}
    with pytest.raises(ConfigError) as err:
        render_multiview_dataset({**ds, "scenes": ["spheres"], "scene_params": crowded}, tmp_path)
    one_line_error(err, "scene_params.spheres", "bound_radius=1.3")
    wide = {**ds["scene_params"], "tabletop": {**ds["scene_params"]["tabletop"], "ring_radius": 1.2}}
    with pytest.raises(ConfigError) as err:
        render_multiview_dataset({**ds, "scenes": ["tabletop"], "scene_params": wide}, tmp_path)
    one_line_error(err, "scene_params.tabletop", "bound_radius=1.3")


def test_tabletop_has_glossy_spheres_and_textured_objects_on_a_textured_ground(ds):
    scene = SCENE_BUILDERS["tabletop"](np.random.default_rng(0), ds["scene_params"]["tabletop"], ds)
    params = ds["scene_params"]["tabletop"]
    glossy = [scene[f"glossy_{k}"]["bsdf"] for k in range(len(params["glossy"]))]
    assert [b["type"] for b in glossy] == ["roughconductor", "roughplastic", "roughconductor", "roughplastic"]
    assert [b["alpha"] for b in glossy] == [g["roughness"] for g in params["glossy"]]
    textured = [scene[f"textured_{k}"]["bsdf"]["bsdf"]["reflectance"]["type"] for k in range(4)]
    assert set(textured) <= {"checkerboard", "bitmap"} and "textured_4" not in scene
    assert scene["ground"]["bsdf"]["reflectance"]["type"] == "checkerboard"
    assert scene["centre"]["bsdf"]["bsdf"]["reflectance"]["type"] in {"checkerboard", "bitmap"}
    assert scene["env"]["type"] == "envmap"


def test_renders_loadable_blender_scenes_and_caches(mitsuba_variant, ds, tmp_path):
    summary = render_multiview_dataset(ds, tmp_path)
    assert summary["scenes_rendered"] == 3 and summary["views_rendered"] == 15
    assert summary["rays"] == 15 * 24 * 24 * 4 and summary["rays_per_second"] > 0
    for scene in ("spheres", "busy", "tabletop"):
        root = tmp_path / scene
        assert sorted(p.name for p in root.iterdir()) == [
            KEY_FILE,
            "test",
            "train",
            "transforms_test.json",
            "transforms_train.json",
            "transforms_val.json",
            "val",
        ]
        meta = json.loads((root / "transforms_train.json").read_text())
        assert meta["camera_angle_x"] == ds["camera_angle_x"]
        assert [f["file_path"] for f in meta["frames"]] == ["./train/r_0", "./train/r_1"]
        for split, n in ds["views"].items():
            data = load_blender_split(root, split)
            assert data.images.shape == (n, 24, 24, 3) and data.alphas.shape == (n, 24, 24)
            np.testing.assert_allclose(data.c2w, split_poses(ds, scene, split), atol=1e-6)
            np.testing.assert_allclose(np.linalg.norm(data.c2w[:, :3, 3], axis=1), ds["radius"], rtol=1e-6)
            assert np.all(data.alphas[:, [0, 0, -1, -1], [0, -1, 0, -1]] == 0)  # corners: background
            assert data.alphas[:, 8:16, 8:16].mean(axis=(1, 2)).min() > 0.2  # objects around the centre
            hit = data.alphas > 0.99
            assert data.images[hit].mean() > 0.02 and data.images[hit].std() > 0.01  # lit, not flat
            # every camera looks at the origin: it projects to the image centre
            for c2w in data.c2w.astype(np.float64):
                np.testing.assert_allclose(project(c2w, data.focal, 24, 24, np.zeros(3)), [12, 12], atol=1e-4)
        test = load_blender_split(root, "test")
        np.testing.assert_allclose(test.c2w[:, 2, 3], ds["radius"] * math.sin(math.radians(30)), rtol=1e-5)

    again = render_multiview_dataset(ds, tmp_path)
    assert again["scenes_rendered"] == 0 and again["scenes_cached"] == 3 and again["rays"] == 0
    assert render_multiview_dataset({**ds, "near": 2.5}, tmp_path)["scenes_rendered"] == 0
    before = (tmp_path / "spheres" / "train" / "r_0.png").read_bytes()
    params = {**ds["scene_params"], "busy": {**ds["scene_params"]["busy"], "n_objects": 6}}
    changed = render_multiview_dataset({**ds, "scene_params": params}, tmp_path)
    assert changed["scenes_rendered"] == 1 and list(changed["per_scene"]) == ["busy"]
    assert (tmp_path / "spheres" / "train" / "r_0.png").read_bytes() == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary folders left
    # A scene the config no longer lists is deleted; a user's own scene folder (no KEY_FILE) stays.
    (tmp_path / "mine" / "train").mkdir(parents=True)
    fewer = render_multiview_dataset({**ds, "scenes": ["spheres", "tabletop"]}, tmp_path)
    assert (fewer["scenes_removed"], fewer["scenes_rendered"]) == (1, 0)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine", "spheres", "tabletop"]
    assert (tmp_path / "spheres" / "train" / "r_0.png").read_bytes() == before


def test_an_interrupted_render_leaves_no_scene(mitsuba_variant, ds, tmp_path, monkeypatch):
    calls = []

    def failing(*args):
        calls.append(1)
        if len(calls) > 1:
            raise KeyboardInterrupt
        return np.zeros((24, 24, 4), np.float32)

    monkeypatch.setattr(multiview, "render_view", failing)
    with pytest.raises(KeyboardInterrupt):
        render_multiview_dataset({**ds, "scenes": ["busy"]}, tmp_path)
    assert list(tmp_path.iterdir()) == []


def probe_scene(rng, params, ds):
    """A small sphere at PROBE lit by a constant environment (a test-only scene)."""
    return {
        "type": "scene",
        "env": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "probe": {
            "type": "sphere",
            "center": PROBE.tolist(),
            "radius": params["radius"],
            "bsdf": {"type": "diffuse"},
        },
    }


def test_objects_land_where_the_json_camera_model_projects_them(mitsuba_variant, ds, tmp_path, monkeypatch):
    monkeypatch.setitem(SCENE_BUILDERS, "probe", probe_scene)
    w, h = 48, 36  # non-square: a swapped axis would show
    probe = {
        **ds,
        "scenes": ["probe"],
        "width": w,
        "height": h,
        "spp": 32,
        "views": {"train": 4, "val": 1, "test": 2},
        "scene_params": {"probe": {"radius": 0.12}},
    }
    render_multiview_dataset(probe, tmp_path)
    for split in ("train", "val", "test"):
        data = load_blender_split(tmp_path / "probe", split)
        rows, cols = np.mgrid[0:h, 0:w]
        for alpha, c2w in zip(data.alphas, data.c2w.astype(np.float64), strict=True):
            assert alpha.sum() > 3 and alpha[[0, 0, -1, -1], [0, -1, 0, -1]].max() == 0
            centroid = np.array([(alpha * (cols + 0.5)).sum(), (alpha * (rows + 0.5)).sum()]) / alpha.sum()
            expected = project(c2w, data.focal, w, h, PROBE)
            # measured error ~0.1 px; rays through pixel corners instead of centres would be 0.5 px off
            assert np.abs(centroid - expected).max() < 0.35, (split, centroid, expected)
            # the ray generate_rays shoots through the nearest pixel centre passes the probe centre
            rays = generate_rays(c2w, data.focal, w, h, 2.0, 6.0)
            col, row = np.floor(expected).astype(int)
            o = rays["origins"][row * w + col].double().numpy()
            d = rays["viewdirs"][row * w + col].double().numpy()
            miss = np.linalg.norm(np.cross(PROBE - o, d))
            pixel = np.linalg.norm(PROBE - o) / data.focal  # one pixel's width at the probe's distance
            assert miss < pixel, (miss, pixel)
            assert torch.isfinite(rays["radii"]).all()
