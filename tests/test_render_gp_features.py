"""The GP filters' features in the AOV integrator (Davletaliyev 2016, Sec. 3.2.1.2): world position and
secondary albedo, with their variances, in closed-form scenes."""

import numpy as np
import pytest
from omegaconf import OmegaConf

from src.render.render_dataset import render_key, scene_sources, still_image_key_extra
from tests.conftest import compose_config
from tests.test_render import render

CAMERA = np.array([0.0, 0.0, 4.0])
NEAR_CLIP = 0.01  # Mitsuba's perspective default
WALL_ALBEDO = (0.2, 0.5, 0.8)


@pytest.fixture(scope="module")
def ds():
    cfg = compose_config(["profile=smoke", "dataset.width=24", "dataset.height=16"])
    return OmegaConf.to_container(cfg.dataset, resolve=True)


def scene_file(ds, tmp_path, name, shapes):
    xml = tmp_path / f"{name}.xml"
    xml.write_text(
        f"""<scene version="3.0.0">
  <sensor type="perspective"><float name="fov" value="45"/>
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
  </sensor>
  <emitter type="constant"><rgb name="radiance" value="1.0"/></emitter>
  {shapes}
</scene>"""
    )
    (source,) = scene_sources({**ds, "bases": [], "scene_files": [str(xml)]})
    return source


def test_position_is_camera_plus_depth_times_direction_on_a_plane(mitsuba_variant, ds, tmp_path):
    """A diffuse plane z = 0 filling the view, 4 units in front of the camera: every sample's position is
    camera + t * direction, so z = 0, |position - camera| = depth (+ the near clip: Mitsuba starts camera
    rays on the near plane, 0.01 away, and `depth` is the hit distance along that ray), and x, y lie at the
    pixel's ray."""
    plane = (
        '<shape type="rectangle"><bsdf type="diffuse"/>'
        '<transform name="to_world"><scale value="10"/></transform></shape>'
    )
    b = render(ds, scene_file(ds, tmp_path, "plane", plane), 8)
    p, depth = b["position"], b["depth"][..., 0]
    assert p.shape == (16, 24, 3) and np.all(depth >= 4.0 - NEAR_CLIP - 1e-4)
    np.testing.assert_allclose(p[..., 2], 0.0, atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(p - CAMERA, axis=-1) - depth, NEAR_CLIP, atol=1.5e-3)
    # Pixel centres: the film spans 2 * 4 * tan(22.5 deg) horizontally at the plane, +x to the right, +y up.
    h, w = depth.shape
    size = 2 * 4 * np.tan(np.radians(22.5)) / w
    x = (np.arange(w) + 0.5 - w / 2) * size
    y = (h / 2 - np.arange(h) - 0.5) * size
    # (8 uniform samples per pixel: the mean's error has std size / sqrt(12 * 8) ~ 0.1 size.)
    for err in (p[..., 0] - x[None, :], p[..., 1] - y[:, None]):
        assert np.abs(err).max() < 0.5 * size and abs(err.mean()) < 0.02 * size
    # The variances of the pixel means: position varies within a pixel, the plane's albedo does not.
    assert b["positionVariance"].shape == (16, 24, 1) and np.all(b["positionVariance"] > 0)
    assert b["positionVariance"].max() < size**2
    # Every mirror ray of the plane (it reflects towards +z) escapes: secondary albedo 0, no variance.
    assert np.all(b["secondary_albedo"] == 0) and np.all(b["secondary_albedoVariance"] == 0)


def test_secondary_albedo_is_the_wall_seen_in_a_mirror_sphere(mitsuba_variant, ds, tmp_path):
    """A perfect mirror sphere at the origin and a coloured diffuse wall behind the camera (z = 8, facing
    it): where the mirror ray of the camera ray hits the wall, the secondary albedo is the wall's albedo;
    where the camera ray escapes, position and secondary albedo are 0."""
    rgb = ", ".join(map(str, WALL_ALBEDO))
    shapes = f"""<shape type="sphere"><bsdf type="conductor"/></shape>
  <shape type="rectangle"><bsdf type="diffuse"><rgb name="reflectance" value="{rgb}"/></bsdf>
    <transform name="to_world"><scale value="20"/><rotate y="1" angle="180"/><translate z="8"/></transform>
  </shape>"""
    b = render(ds, scene_file(ds, tmp_path, "mirror", shapes), 8)
    hit = b["depth"][..., 0] > 0
    sky = b["depth"][..., 0] == 0
    assert sky.sum() > 20 and hit.sum() > 20
    assert np.all(b["position"][sky] == 0) and np.all(b["secondary_albedo"][sky] == 0)
    # Sphere pixels facing the camera: the mirror rays go back towards +z and hit the wall.
    facing = hit & (b["normal"][..., 2] > 0.9)
    assert facing.sum() >= 4
    np.testing.assert_allclose(
        b["secondary_albedo"][facing], np.broadcast_to(WALL_ALBEDO, (facing.sum(), 3)), atol=1e-5
    )
    assert b["secondary_albedoVariance"][facing].max() < 1e-6  # 0 but for float32 cancellation
    # The primary albedo there is the mirror's (1), the position on the unit sphere.
    np.testing.assert_allclose(np.linalg.norm(b["position"][facing], axis=-1), 1.0, atol=2e-3)
    # Near the silhouette the mirror rays go away from the wall and escape: 0, and silhouette pixels that
    # mix wall and escape samples get a variance.
    grazing = hit & (b["normal"][..., 2] < 0.3) & (b["normal"][..., 2] > 0)
    assert grazing.any() and np.all(b["secondary_albedo"][grazing].max(-1) < max(WALL_ALBEDO))
    assert b["secondary_albedoVariance"][hit].max() > 0


def test_render_key_tracks_the_written_buffers(ds):
    """The still-image files depend on the buffers the integrator writes: files from before position and
    secondary albedo were added get a different key and are rendered again."""
    identity = {"base": "tabletop", "seed": 1}
    old = {"buffers": ["diffuse", "specular", "albedo", "normal", "depth", "visibility"]}
    assert "position" in still_image_key_extra()["buffers"]
    assert render_key(identity, ds, 4, "noisy", still_image_key_extra()) != render_key(
        identity, ds, 4, "noisy", old
    )
