"""The AOV integrator, the sample statistics and the dataset renderer, on tiny renders."""

import numpy as np
import pytest
from omegaconf import OmegaConf

from src.errors import ConfigError, DataError
from src.render.render_dataset import (
    SceneSource,
    load_scene,
    pass_seed,
    render_buffers,
    render_denoise_dataset,
    render_key,
    scene_sources,
    split_passes,
)
from tests.conftest import compose_config, one_line_error


@pytest.fixture(scope="module")
def ds():
    cfg = compose_config(["profile=smoke", "dataset.width=24", "dataset.height=16"])
    return OmegaConf.to_container(cfg.dataset, resolve=True)


def render(ds, source, spp, role="noisy", max_pass=1 << 24):
    import mitsuba as mi

    scene, sensor = load_scene(source, ds)
    integrator = mi.load_dict({"type": "kpcn_aov", **ds["integrator"]})
    passes = split_passes(spp, ds["width"] * ds["height"], max_pass)
    seeds = [pass_seed(ds["seed"], source.name, spp, role, i) for i in range(len(passes))]
    return render_buffers(scene, sensor, integrator, spp, seeds, passes)


def test_render_key_tracks_each_base_scenes_constants(ds):
    """A change in `dataset.base_scenes.<base>` re-renders that base only; user scene files ignore it."""
    tabletop, outdoor = {"base": "tabletop", "seed": 1}, {"base": "outdoor", "seed": 1}
    bases = {**ds["base_scenes"], "tabletop": {**ds["base_scenes"]["tabletop"], "sky_scale": 0.5}}
    changed = {**ds, "base_scenes": bases}
    assert render_key(tabletop, changed, 4, "noisy") != render_key(tabletop, ds, 4, "noisy")
    assert render_key(outdoor, changed, 4, "noisy") == render_key(outdoor, ds, 4, "noisy")
    user = {"file": "a.xml", "sha256": "0"}
    assert render_key(user, changed, 4, "noisy") == render_key(user, ds, 4, "noisy")


def test_passes_respect_the_wavefront_budget():
    passes = split_passes(8192, 1280 * 720, 1 << 24)
    assert sum(passes) == 8192 and max(passes) * 1280 * 720 <= 1 << 24
    assert split_passes(5, 10, 1000) == [5]


def test_reference_seeds_are_independent_of_noisy_seeds():
    noisy = {pass_seed(0, "cornell-0000", spp, "noisy", i) for spp in (4, 8, 16) for i in range(4)}
    reference = {pass_seed(0, "cornell-0000", 4096, "reference", i) for i in range(64)}
    assert len(noisy) == 12 and len(reference) == 64 and not noisy & reference
    assert pass_seed(0, "a", 4, "noisy", 0) != pass_seed(0, "a", 4, "reference", 0)


def test_color_is_diffuse_plus_specular_and_lobes_split(mitsuba_variant, ds):
    # Seeded outdoor scenes have glossy and diffuse materials; both buffers must receive light.
    b = render(ds, SceneSource("outdoor-0000", base="outdoor", seed=11), 16)
    np.testing.assert_allclose(b["color"], b["diffuse"] + b["specular"], rtol=1e-5, atol=1e-6)
    assert b["diffuse"].sum() > 0 and b["specular"].sum() > 0
    assert set(b) >= {"albedo", "normal", "depth", "visibility", "colorVariance", "visibilityVariance"}
    assert b["color"].shape == (16, 24, 3) and b["depth"].shape == (16, 24, 1)
    norms = np.linalg.norm(b["normal"], axis=-1)
    hit = b["depth"][..., 0] > 0
    assert np.all(norms[hit] <= 1.0 + 1e-4) and np.all((b["visibility"] >= 0) & (b["visibility"] <= 1))


def test_variance_of_mean_shrinks_as_one_over_spp(mitsuba_variant, ds):
    source = SceneSource("cornell-0000", base="cornell", seed=3)
    low, high = render(ds, source, 16), render(ds, source, 128)
    noisy = (low["colorVariance"] > 0) & (high["colorVariance"] > 0)
    ratio = low["colorVariance"][noisy].sum() / high["colorVariance"][noisy].sum()
    assert 5.0 < ratio < 12.0  # expected 128 / 16 = 8


def test_reference_is_closer_to_high_spp_truth_than_noisy_inputs(mitsuba_variant, ds):
    source = SceneSource("tabletop-0000", base="tabletop", seed=5)
    truth = render(ds, source, 1024, role="reference")["color"]
    reference = render(ds, source, 256, role="reference", max_pass=24 * 16 * 64)["color"]
    noisy = render(ds, source, 8)["color"]
    assert np.mean((reference - truth) ** 2) < 0.25 * np.mean((noisy - truth) ** 2)


def test_dataset_render_writes_kpcn_exrs_and_caches(mitsuba_variant, ds, tmp_path):
    from src.data.kpcn_buffers import KPCN_BUFFERS, load_kpcn_exr
    from src.io.exr import exr_channel_names

    small = {**ds, "bases": ["cornell"], "noisy_spp": [2, 4], "reference_spp": 8}
    first = render_denoise_dataset(small, tmp_path)
    assert first["files_rendered"] == 3 and first["samples_per_second"] > 0
    path = tmp_path / "cornell-0000-00004spp.exr"
    expected = {ch for chans in KPCN_BUFFERS.values() for ch in chans}
    assert expected <= set(exr_channel_names(path))
    buffers, _ = load_kpcn_exr(path)
    assert buffers["color"].shape == (16, 24, 3)
    again = render_denoise_dataset(small, tmp_path)
    assert again["files_rendered"] == 0 and again["files_cached"] == 3
    changed = render_denoise_dataset({**small, "reference_spp": 16}, tmp_path)
    assert changed["files_rendered"] == 1  # only the new reference


def test_user_scene_file_goes_through_the_same_integrator(mitsuba_variant, ds, tmp_path):
    xml = tmp_path / "my_scene.xml"
    xml.write_text(
        """<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
  <shape type="sphere"><bsdf type="roughplastic"><float name="alpha" value="0.1"/></bsdf></shape>
</scene>"""
    )
    (source,) = scene_sources({**ds, "bases": [], "scene_files": [str(xml)]})
    b = render(ds, source, 8)
    hit = b["depth"][..., 0] > 0
    assert 0 < hit.mean() < 1 and b["specular"][hit].sum() > 0 and b["diffuse"][hit].sum() > 0


def test_bad_scene_inputs_give_one_line_errors(mitsuba_variant, ds, tmp_path):
    bad = tmp_path / "broken.xml"
    bad.write_text("<scene version='3.0.0'><shape type='no_such_plugin'/></scene>")
    (source,) = scene_sources({**ds, "bases": [], "scene_files": [str(bad)]})
    with pytest.raises(DataError) as err:
        load_scene(source, ds)
    one_line_error(err, str(bad))
    with pytest.raises(DataError) as err:
        scene_sources({**ds, "scene_files": [str(tmp_path / "missing.xml")]})
    one_line_error(err, "dataset.scene_files", str(tmp_path / "missing.xml"), "not found")
    with pytest.raises(ConfigError) as err:
        render_denoise_dataset({**ds, "noisy_spp": [4, 64], "reference_spp": 32}, tmp_path)
    one_line_error(err, "dataset.noisy_spp=[4, 64]", "dataset.reference_spp=32")
    assert not any(tmp_path.glob("*.exr"))  # checked before anything is rendered


def test_same_config_and_seed_give_the_same_numbers(mitsuba_variant, ds):
    source = SceneSource("outdoor-0001", base="outdoor", seed=21)
    a, b = render(ds, source, 8), render(ds, source, 8)
    for name in a:
        np.testing.assert_array_equal(a[name], b[name], err_msg=name)
    other = render(ds, source, 8, role="reference")
    assert not np.array_equal(a["color"], other["color"])


@pytest.mark.parametrize(
    ("bsdf", "lobe", "empty"), [("diffuse", "diffuse", "specular"), ("roughconductor", "specular", "diffuse")]
)
def test_first_bounce_lobe_decides_the_buffer(mitsuba_variant, ds, tmp_path, bsdf, lobe, empty):
    xml = tmp_path / f"{bsdf}.xml"
    xml.write_text(
        f"""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="30"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
  <shape type="sphere"><bsdf type="{bsdf}"/></shape>
</scene>"""
    )
    (source,) = scene_sources({**ds, "bases": [], "scene_files": [str(xml)]})
    b = render(ds, source, 8)
    # Pixels well inside the silhouette (3x3 erosion): edge pixels also average in directly seen sky.
    hit = np.pad(b["depth"][..., 0] > 0, 1)
    h, w = b["depth"].shape[:2]
    inside = np.all(
        [hit[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 0
    )
    assert inside.sum() > 10
    assert b[lobe][inside].min() > 0 and np.all(b[empty][inside] == 0)
    # Albedo is a reflectance: never above 1 (a BRDF value at its glossy peak would be).
    assert b["albedo"][inside].min() > 0 and b["albedo"][inside].max() <= 1.0 + 1e-3


def test_render_key_tracks_the_albedo_samples(ds):
    """A new `dataset.integrator.albedo_samples` re-renders every file (procedural and user scenes)."""
    changed = {
        **ds,
        "integrator": {**ds["integrator"], "albedo_samples": ds["integrator"]["albedo_samples"] + 1},
    }
    for identity in ({"base": "tabletop", "seed": 1}, {"file": "a.xml", "sha256": "0"}):
        assert render_key(identity, changed, 4, "noisy") != render_key(identity, ds, 4, "noisy")


def bsdf_xml(kind: str, material: str | None = None, alpha: float | None = None) -> str:
    """A Mitsuba XML ``<bsdf>`` of type ``kind`` with an optional conductor preset and GGX alpha."""
    material_xml = f'<string name="material" value="{material}"/>' if material else ""
    alpha_xml = f'<float name="alpha" value="{alpha}"/>' if alpha else ""
    return f'<bsdf type="{kind}">{material_xml}{alpha_xml}</bsdf>'


def sphere_on_floor(ds, tmp_path, bsdf: str):
    """A unit sphere with ``bsdf`` (XML) standing on a diffuse floor under a sky and a sun: what the sphere
    reflects or refracts is path traced, so its colour is noisy. Returns the scene source and a function
    giving the pixels that see only the sphere."""
    xml = tmp_path / "sphere.xml"
    xml.write_text(
        f"""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 1.5, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="0.5"/></emitter>
  <emitter type="directional">
    <vector name="direction" value="-1, -2, -1"/><rgb name="irradiance" value="3"/>
  </emitter>
  <shape type="sphere">{bsdf}</shape>
  <shape type="rectangle"><bsdf type="diffuse"/>
    <transform name="to_world"><rotate x="1" angle="-90"/><scale value="6"/><translate y="-1"/></transform>
  </shape>
</scene>"""
    )
    (source,) = scene_sources({**ds, "bases": [], "scene_files": [str(xml)]})

    def sphere_pixels(b):
        # Every sample of a floor pixel has the normal +Y exactly; erode by one pixel so that no pixel on
        # the silhouette (mixing sphere, floor or sky samples) remains.
        n = b["normal"]
        sphere = (b["depth"][..., 0] > 0) & ((np.abs(n[..., 1] - 1) > 1e-4) | (np.abs(n[..., 0]) > 1e-4))
        h, w = sphere.shape
        pad = np.pad(sphere, 1)
        inside = np.all(
            [pad[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w] for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 0
        )
        assert inside.sum() > 20
        return inside

    return source, sphere_pixels


def relative_variance(b, name, pixels):
    """Mean variance of the pixel mean over ``pixels``, relative to the squared mean there."""
    return b[f"{name}Variance"][pixels].mean() / np.square(b[name][pixels].mean())


@pytest.mark.parametrize(
    "bsdf",
    [bsdf_xml("conductor", "Au"), bsdf_xml("roughconductor", "Au", 0.3), bsdf_xml("dielectric")],
    ids=["conductor", "roughconductor", "dielectric"],
)
def test_glossy_and_glass_albedo_is_far_less_noisy_than_colour(mitsuba_variant, ds, tmp_path, bsdf):
    """The albedo of a glossy or glass first hit is a several-sample estimate of its directional albedo,
    so it carries far less noise than the colour; a smooth dielectric's is R + T = 1 exactly."""
    source, sphere_pixels = sphere_on_floor(ds, tmp_path, bsdf)
    b = render(ds, source, 8)
    inside = sphere_pixels(b)
    albedo, colour = relative_variance(b, "albedo", inside), relative_variance(b, "color", inside)
    assert colour > 0 and albedo < colour / 20, (albedo, colour)
    assert b["albedo"][inside].min() > 0 and b["albedo"][inside].max() <= 1.0 + 1e-4
    if bsdf == bsdf_xml("dielectric"):
        np.testing.assert_allclose(b["albedo"][inside], 1.0, atol=1e-5)


@pytest.mark.parametrize(
    "bsdf",
    [bsdf_xml("roughconductor", "Cu", 0.5), bsdf_xml("roughdielectric", alpha=0.5)],
    ids=["roughconductor", "roughdielectric"],
)
def test_albedo_samples_cut_the_albedo_variance(mitsuba_variant, ds, tmp_path, bsdf):
    """`albedo_samples: 16` (stratified) against one BSDF sample per camera sample: same mean, several
    times less variance. 48x32 pixels, because the one-sample albedo of a rough dielectric is 1 but for
    rare shadowed microfacets, so its variance needs many samples to be measured."""
    ds = {**ds, "width": 48, "height": 32}
    source, sphere_pixels = sphere_on_floor(ds, tmp_path, bsdf)
    one = render({**ds, "integrator": {**ds["integrator"], "albedo_samples": 1}}, source, 8)
    many = render({**ds, "integrator": {**ds["integrator"], "albedo_samples": 16}}, source, 8)
    inside = sphere_pixels(one) & sphere_pixels(many)
    ratio = one["albedoVariance"][inside].mean() / many["albedoVariance"][inside].mean()
    assert ratio > 5, ratio
    assert abs(one["albedo"][inside].mean() - many["albedo"][inside].mean()) < 0.02
