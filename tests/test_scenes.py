"""The procedural scene family: deterministic per seed, varied across seeds, all materials covered."""

import numpy as np
import pytest

from src.errors import ConfigError
from src.render.scenes import BASE_SCENES, build_procedural_scene, value_noise
from tests.conftest import compose_config


@pytest.fixture(scope="module")
def rnd():
    from omegaconf import OmegaConf

    return OmegaConf.to_container(compose_config(["profile=smoke"]).dataset.randomize, resolve=True)


def _materials(scene: dict) -> list[str]:
    return [v["bsdf"]["type"] for k, v in scene.items() if k.startswith("object_")]


def test_value_noise_is_normalised_and_seeded():
    a = value_noise(np.random.default_rng(1), 33, 3)
    assert a.shape == (33, 33) and a.min() == 0 and a.max() == 1
    np.testing.assert_array_equal(a, value_noise(np.random.default_rng(1), 33, 3))


def test_same_seed_same_scene_and_seeds_vary_the_scene(mitsuba_variant, rnd):
    for base in BASE_SCENES:
        a, b = build_procedural_scene(base, 7, rnd), build_procedural_scene(base, 7, rnd)
        assert str(a["sensor"]) == str(b["sensor"]) and _materials(a) == _materials(b)
        cameras = {str(build_procedural_scene(base, s, rnd)["sensor"]["to_world"]) for s in range(5)}
        assert len(cameras) == 5


def test_scene_family_covers_every_material(mitsuba_variant, rnd):
    seen = set()
    for seed in range(12):
        for base in BASE_SCENES:
            seen.update(_materials(build_procedural_scene(base, seed, rnd)))
    assert seen == {"diffuse", "roughconductor", "roughdielectric", "roughplastic"}


def test_unknown_base_or_material_is_a_config_error(mitsuba_variant, rnd):
    with pytest.raises(ConfigError, match="dataset.bases"):
        build_procedural_scene("kitchen", 0, rnd)
    with pytest.raises(ConfigError, match="velvet"):
        build_procedural_scene("outdoor", 0, {**rnd, "materials": ["velvet"], "n_objects": [2, 2]})
