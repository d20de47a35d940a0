"""The procedural scene family: deterministic per seed, varied across seeds, all materials covered."""

import numpy as np
import pytest

from src.errors import ConfigError
from src.render.scenes import BASE_SCENES, build_procedural_scene, value_noise
from tests.conftest import compose_config


@pytest.fixture(scope="module")
def ds():
    from omegaconf import OmegaConf

    return OmegaConf.to_container(compose_config(["profile=smoke"]).dataset, resolve=True)


def _materials(scene: dict) -> list[str]:
    return [v["bsdf"]["type"] for k, v in scene.items() if k.startswith("object_")]


def test_value_noise_is_normalised_and_seeded():
    a = value_noise(np.random.default_rng(1), 33, 3, 4, 0.5)
    assert a.shape == (33, 33) and a.min() == 0 and a.max() == 1
    np.testing.assert_array_equal(a, value_noise(np.random.default_rng(1), 33, 3, 4, 0.5))
    assert not np.array_equal(a, value_noise(np.random.default_rng(1), 33, 3, 4, 0.8))


def test_same_seed_same_scene_and_seeds_vary_the_scene(mitsuba_variant, ds):
    for base in BASE_SCENES:
        a, b = build_procedural_scene(base, 7, ds), build_procedural_scene(base, 7, ds)
        assert str(a["sensor"]) == str(b["sensor"]) and _materials(a) == _materials(b)
        cameras = {str(build_procedural_scene(base, s, ds)["sensor"]["to_world"]) for s in range(5)}
        assert len(cameras) == 5


def test_scene_family_covers_every_material(mitsuba_variant, ds):
    seen = set()
    for seed in range(12):
        for base in BASE_SCENES:
            seen.update(_materials(build_procedural_scene(base, seed, ds)))
    assert seen == {"diffuse", "roughconductor", "roughdielectric", "roughplastic"}


def test_unknown_base_or_material_is_a_config_error(mitsuba_variant, ds):
    with pytest.raises(ConfigError, match="dataset.bases"):
        build_procedural_scene("kitchen", 0, ds)
    with pytest.raises(ConfigError, match="velvet"):
        rnd = {**ds["randomize"], "materials": ["velvet"], "n_objects": [2, 2]}
        build_procedural_scene("outdoor", 0, {**ds, "randomize": rnd})
    with pytest.raises(ConfigError, match="dataset.base_scenes.outdoor"):
        build_procedural_scene("outdoor", 0, {**ds, "base_scenes": {}})


def _with(ds: dict, path: str, value) -> dict:
    """A deep copy of ``ds`` with the dotted key ``path`` set to ``value``."""
    import copy

    out = copy.deepcopy(ds)
    *parents, leaf = path.split(".")
    node = out
    for key in parents:
        node = node[key]
    node[leaf] = value
    return out


def test_moved_constants_are_read_from_config(mitsuba_variant, ds):
    """The layout, light, camera and colour constants come from `dataset.base_scenes` / `randomize`: changing
    one through config changes the built scene (same seed)."""
    tabletop = build_procedural_scene("tabletop", 3, ds)
    brighter = build_procedural_scene("tabletop", 3, _with(ds, "base_scenes.tabletop.light.radiance", 30.0))
    light, bright = (
        tabletop["light"]["emitter"]["radiance"]["value"],
        brighter["light"]["emitter"]["radiance"]["value"],
    )
    assert bright == [2 * v for v in light]
    dimmer_sky = build_procedural_scene("tabletop", 3, _with(ds, "base_scenes.tabletop.sky_scale", 0.5))
    assert tabletop["sky"]["scale"] == 0.2 and dimmer_sky["sky"]["scale"] == 0.5
    farther = build_procedural_scene("outdoor", 3, _with(ds, "base_scenes.outdoor.camera.distance", 8.0))
    assert str(farther["sensor"]["to_world"]) != str(
        build_procedural_scene("outdoor", 3, ds)["sensor"]["to_world"]
    )
    cornell = _with(ds, "base_scenes.cornell.objects.ground_y", -0.5)
    moved = build_procedural_scene("cornell", 3, cornell)["object_0"]["to_world"]
    assert str(moved) != str(build_procedural_scene("cornell", 3, ds)["object_0"]["to_world"])
    gold = _with(_with(ds, "randomize.conductors", ["Au"]), "randomize.materials", ["conductor"])
    objects = [v for k, v in build_procedural_scene("outdoor", 3, gold).items() if k.startswith("object_")]
    assert objects and {o["bsdf"]["material"] for o in objects} == {"Au"}
    grey = _with(_with(ds, "randomize.textured_probability", 0.0), "randomize.color", [0.5, 0.5])
    grey = _with(_with(grey, "randomize.materials", ["diffuse"]), "randomize.sphere_probability", 1.0)
    objects = [v for k, v in build_procedural_scene("outdoor", 3, grey).items() if k.startswith("object_")]
    assert {o["type"] for o in objects} == {"sphere"}
    assert all(o["bsdf"]["reflectance"]["value"] == [0.5, 0.5, 0.5] for o in objects)
