"""The volumetric scene family: noise grids (range, determinism, spectrum, Worley and height-fog closed
forms), animated scenes (deterministic per seed, frames and seeds differ, every base renders with visible
media through Mitsuba's volpath) and screen-space motion vectors (closed forms and Mitsuba's camera)."""

import numpy as np
import pytest

from src.errors import ConfigError
from src.render import volume_grids as vg
from tests.conftest import compose_config

# --- grids (numpy only) ------------------------------------------------------------------------------------


def _points(n=2000, seed=0, scale=16.0):
    return np.random.default_rng(seed).uniform(0, scale, (n, 3))


def test_value_noise_interpolates_its_lattice_and_stays_in_unit_range():
    lattice = vg.noise_lattices(np.random.default_rng(0), 1, dims=3)[0]
    corners = np.random.default_rng(1).integers(0, 40, (50, 3)).astype(float)  # wraps past the period
    idx = (corners.astype(int) % vg.LATTICE_PERIOD) @ (vg.LATTICE_PERIOD ** np.arange(3))
    np.testing.assert_allclose(vg.value_noise_nd(corners, lattice), lattice[idx])
    values = vg.value_noise_nd(_points(), lattice)
    assert values.min() >= 0 and values.max() <= 1
    # Continuous: a tiny step moves the value a tiny amount.
    p = _points(200)
    assert np.abs(vg.value_noise_nd(p + 1e-4, lattice) - vg.value_noise_nd(p, lattice)).max() < 1e-2


def test_fbm_is_in_unit_range_deterministic_per_seed_and_periodic():
    lat = vg.noise_lattices(np.random.default_rng(3), 4)
    p = _points()
    a = vg.fbm(p, lat, 0.5, time=0.3)
    assert a.min() >= 0 and a.max() <= 1 and a.std() > 0.05
    np.testing.assert_array_equal(a, vg.fbm(p, vg.noise_lattices(np.random.default_rng(3), 4), 0.5, time=0.3))
    assert not np.allclose(a, vg.fbm(p, vg.noise_lattices(np.random.default_rng(4), 4), 0.5, time=0.3))
    assert not np.allclose(a, vg.fbm(p, lat, 0.5, time=0.8))  # the 4th axis evolves the field
    # Periodic tables: advecting by one period is the same field (no seams when the wind carries it).
    np.testing.assert_allclose(vg.fbm(p + vg.LATTICE_PERIOD, lat, 0.5, time=0.3), a, atol=1e-12)


def _high_frequency_fraction(octaves, persistence=0.5):
    """Share of a 1-D fBm transect's power above the first octave's lattice frequency (1 cycle/unit)."""
    n = 1024  # 64 samples per unit over exactly one lattice period: a seamless FFT
    x = np.arange(n) / n * vg.LATTICE_PERIOD
    p = np.stack([x, np.full(n, 3.3), np.full(n, 7.1)], -1)
    lat = vg.noise_lattices(np.random.default_rng(0), octaves)
    signal = vg.fbm(p, lat, persistence)
    power = np.abs(np.fft.rfft(signal - signal.mean())) ** 2
    freq = np.fft.rfftfreq(n, d=vg.LATTICE_PERIOD / n)
    return power[freq > 1.0].sum() / power.sum()


def test_fbm_octaves_add_high_frequencies_in_proportion_to_persistence():
    one, two, four = (_high_frequency_fraction(o) for o in (1, 2, 4))
    assert one < 0.05  # one octave of value noise: its power sits below the lattice frequency
    assert one < two < four
    assert _high_frequency_fraction(4, persistence=0.25) < four < _high_frequency_fraction(4, persistence=0.8)


def test_worley_is_the_distance_to_the_nearest_feature_point():
    cells = 4
    features = vg.worley_points(np.random.default_rng(5), cells)
    absolute = (np.stack(np.meshgrid(*[np.arange(cells)] * 3, indexing="ij"), -1) + features).reshape(-1, 3)
    shifts = np.stack(np.meshgrid(*[[-cells, 0, cells]] * 3, indexing="ij"), -1).reshape(-1, 3)
    images = (absolute[:, None, :] + shifts[None]).reshape(-1, 3)  # periodic copies
    p = _points(300, scale=cells)
    brute = np.linalg.norm(p[:, None, :] - images[None], axis=-1).min(1)
    np.testing.assert_allclose(vg.worley(p, features), brute)
    np.testing.assert_allclose(vg.worley(absolute[:20], features), 0.0, atol=1e-12)


def test_height_fog_decays_with_height_as_the_closed_form():
    box = vg.Box((0.0, 1.5, 0.0), (6.0, 3.0, 6.0))
    p = vg.voxel_centres(box, vg.grid_shape(box, 24))
    h = p[..., 1] - box.lower[1]
    noise = np.random.default_rng(0).random(h.shape)
    np.testing.assert_allclose(vg.height_fog_density(h, 0.7, noise, 0.0), np.exp(-h / 0.7))
    modulated = vg.height_fog_density(h, 0.7, noise, 0.5)
    assert modulated.min() >= 0 and modulated.max() <= 1
    layers = modulated.mean(axis=(0, 2))  # per height (axis 1 of [z, y, x])
    assert np.all(np.diff(layers) < 0)


def test_voxel_centres_match_the_gridvolume_transform():
    box = vg.Box((1.0, 2.0, -1.0), (4.0, 2.0, 1.0))
    shape = vg.grid_shape(box, 16)
    assert shape == (4, 8, 16)  # [z, y, x], 16 along the longest side, at least 4
    nz, ny, nx = shape
    unit = np.array([(3 + 0.5) / nx, (2 + 0.5) / ny, (1 + 0.5) / nz, 1.0])
    np.testing.assert_allclose((vg.box_to_world(box) @ unit)[:3], vg.voxel_centres(box, shape)[1, 2, 3])


def test_cloud_plume_haze_and_albedo_stay_in_unit_range():
    rng = np.random.default_rng(0)
    local = rng.uniform(-1, 1, (500, 3))
    n1, n2 = rng.random(500), rng.random(500)
    for d in (
        vg.cloud_density(local, n1, n2, 0.55, 0.25),
        vg.plume_density(local, n1, 0.12, 0.35, rng.uniform(-0.3, 0.3, (500, 2)), 0.7),
        vg.haze_density(n1, 0.2),
    ):
        assert d.min() >= 0 and d.max() <= 1 and d.max() > 0
    albedo = vg.albedo_grid(n1, [0.5, 0.6, 0.7], [0.9, 0.95, 1.0])
    assert albedo.shape == (500, 3) and albedo.min() >= 0.5 and albedo.max() <= 1.0


# --- scenes (Mitsuba) --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def ds():
    from omegaconf import OmegaConf

    cfg = compose_config(["profile=smoke", "dataset=volumetric", "dataset.grid_res=16", "dataset.frames=8"])
    return OmegaConf.to_container(cfg.dataset, resolve=True)


def _grids(scene):
    """The density grids (numpy) of a scene's media: the scene-wide one and any box interiors."""
    from src.render.volume_scenes import ATMOSPHERE

    media = [scene[ATMOSPHERE]] if ATMOSPHERE in scene else []
    media += [v["interior"] for v in scene.values() if isinstance(v, dict) and "interior" in v]
    assert media
    return [np.array(m["sigma_t"]["grid"]) for m in media] + [np.array(m["albedo"]["grid"]) for m in media]


def _camera_matrix(scene):
    return np.array(scene["sensor"]["to_world"].matrix)


BASES = ["cloud", "smoke_tabletop", "fog_objects", "godrays"]


@pytest.mark.parametrize("base", BASES)
def test_frames_are_deterministic_and_vary_with_frame_and_seed(mitsuba_variant, ds, base):
    from src.render.volume_scenes import build_volumetric_frame, camera_at

    a, b = build_volumetric_frame(base, 3, 2, ds), build_volumetric_frame(base, 3, 2, ds)
    for ga, gb in zip(_grids(a), _grids(b), strict=True):
        np.testing.assert_array_equal(ga, gb)
        assert ga.min() >= 0 and ga.max() <= 1
    np.testing.assert_array_equal(_camera_matrix(a), _camera_matrix(b))
    np.testing.assert_allclose(_camera_matrix(a), camera_at(base, 3, 2, ds).to_world, atol=1e-6)
    later, other = build_volumetric_frame(base, 3, 3, ds), build_volumetric_frame(base, 4, 2, ds)
    assert not np.array_equal(_grids(a)[0], _grids(later)[0])  # the media drift and evolve
    assert not np.allclose(_camera_matrix(a), _camera_matrix(later))  # the camera moves
    assert not np.allclose(_camera_matrix(a), _camera_matrix(other))
    assert not all(
        np.array_equal(x, y) for x, y in zip(_grids(a), _grids(other), strict=True) if x.shape == y.shape
    )
    # Only the camera and media move: everything else is the same scene in every frame.
    assert sorted(a) == sorted(later)


def test_unknown_base_and_frame_outside_the_animation_are_config_errors(mitsuba_variant, ds):
    from src.render.volume_scenes import build_volumetric_frame, camera_at

    with pytest.raises(ConfigError, match="dataset.bases"):
        build_volumetric_frame("volcano", 0, 0, ds)
    with pytest.raises(ConfigError, match="dataset.frames"):
        camera_at("cloud", 0, ds["frames"], ds)
    with pytest.raises(ConfigError, match="dataset.base_scenes.godrays"):
        build_volumetric_frame("godrays", 0, 0, {**ds, "base_scenes": {}})


def _render(scene, size=16, spp=32, seed=0):
    import mitsuba as mi

    scene = dict(scene)
    scene["sensor"] = {**scene["sensor"], "film": {"type": "hdrfilm", "width": size, "height": size}}
    scene["integrator"] = {"type": "volpath", "max_depth": 12}
    return np.array(mi.render(mi.load_dict(scene), spp=spp, seed=seed))


@pytest.mark.parametrize("base", BASES)
def test_every_base_renders_with_visible_media(mitsuba_variant, ds, base):
    from src.render.volume_scenes import build_volumetric_frame, strip_media

    # Seed 3: at 16x16 pixels each base's medium covers a good part of the frame (a small cloud can be
    # about as bright as the sky behind it; test_thick_and_thin_media checks every seed's optical depth).
    scene = build_volumetric_frame(base, 3, 0, ds)
    with_media, again, without = _render(scene), _render(scene, seed=1), _render(strip_media(scene))
    assert np.isfinite(with_media).all() and with_media.min() >= 0 and with_media.mean() > 0.01
    # On 4x4-pixel block medians (robust to the fireflies of bright, forward-scattering media) the medium
    # changes the image clearly more than Monte Carlo noise does (the same scene, another sampler seed).
    media, noise, surfaces = (
        np.median(img.reshape(4, 4, 4, 4, 3).transpose(0, 2, 1, 3, 4).reshape(4, 4, -1), axis=-1)
        for img in (with_media, again, without)
    )
    change, jitter = (np.abs(media - other).mean() / surfaces.mean() for other in (surfaces, noise))
    assert change > 2 * jitter and change > 0.05, (change, jitter)


def _optical_depth_along_x(medium, y_fraction, x_from=0.0):
    """Optical depth of a medium dict along +x at height ``y_fraction`` of its box and its middle z, from
    ``x_from`` (fraction of the box) to its far side."""
    density = np.array(medium["sigma_t"]["grid"])
    nz, ny, nx = density.shape[:3]
    width = np.array(medium["sigma_t"]["to_world"].matrix)[0, 0]
    row = density[nz // 2, int(y_fraction * (ny - 1)), int(x_from * nx) :].ravel()
    return row.sum() * width / nx * medium["scale"]


def test_thick_and_thin_media(mitsuba_variant, ds):
    """The cloud is optically thick through its middle; the fog near the ground and the haze are thin over
    half their box, so the objects in them stay visible."""
    from src.render.volume_scenes import ATMOSPHERE, build_volumetric_frame

    for seed in range(4):
        assert (
            _optical_depth_along_x(build_volumetric_frame("cloud", seed, 0, ds)["cloud"]["interior"], 0.5) > 5
        )
        for base, height in (("fog_objects", 0.1), ("godrays", 0.25)):
            tau = _optical_depth_along_x(build_volumetric_frame(base, seed, 0, ds)[ATMOSPHERE], height, 0.5)
            assert 0.05 < tau < 2.5, (base, seed, tau)


# --- cameras and motion vectors ----------------------------------------------------------------------------


def test_projection_matches_mitsubas_perspective_camera(mitsuba_variant):
    import mitsuba as mi

    from src.render.volume_camera import Camera, look_at, project

    width, height = 12, 8  # non-square
    camera = Camera(look_at([1.0, 2.0, 3.0], [0.2, 0.5, -0.4]), 50.0)
    sensor = mi.load_dict({**camera.sensor(), "film": {"type": "hdrfilm", "width": width, "height": height}})
    pixels = np.array([[0.5, 0.5], [11.5, 0.5], [3.25, 6.75], [6.0, 4.0]])
    for px in pixels:
        ray, _ = sensor.sample_ray(
            0.0, 0.5, mi.Point2f(float(px[0] / width), float(px[1] / height)), mi.Point2f(0.5)
        )
        point = np.array(ray.o).ravel() + 4.0 * np.array(ray.d).ravel()
        uv, depth = project(point, camera, width, height)
        np.testing.assert_allclose(uv, px, atol=1e-3)
        assert depth > 0


def _plane_positions(camera, width, height, depth):
    """World positions seen through each pixel centre of ``camera`` on the plane at ``depth`` ahead of it
    (camera frame: +x left, +y up, +z ahead, as Mitsuba's look_at)."""
    f = width / (2 * np.tan(np.radians(camera.fov) / 2))
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    local = np.stack([-(u - width / 2) / f, -(v - height / 2) / f, np.ones_like(u)], -1) * depth
    return local @ camera.to_world[:3, :3].T + camera.to_world[:3, 3], f


def test_motion_vectors_of_a_camera_translation_are_the_closed_form():
    from src.render.volume_camera import Camera, look_at, motion_vectors

    width, height, depth = 16, 10, 5.0
    cam_t = Camera(look_at([0, 0, 0], [0, 0, 1]), 45.0)  # +x world is the image's left
    dx, dy = 0.1, 0.05  # the camera moves to the image's right and up
    cam_t1 = Camera(look_at([-dx, dy, 0], [-dx, dy, 1]), 45.0)
    positions, f = _plane_positions(cam_t, width, height, depth)
    flow = motion_vectors(positions, cam_t, cam_t1, width, height)
    assert flow.shape == (height, width, 2)
    # The scene slides the other way: left (-x) and down (+y), by focal length x shift / depth.
    np.testing.assert_allclose(flow[..., 0], -dx * f / depth, atol=1e-9)
    np.testing.assert_allclose(flow[..., 1], dy * f / depth, atol=1e-9)


def test_motion_vectors_of_a_camera_pan_are_the_rotation_homography():
    from src.render.volume_camera import Camera, look_at, motion_vectors

    width, height, theta = 20, 12, np.radians(3.0)
    cam_t = Camera(look_at([0, 0, 0], [0, 0, 1]), 60.0)
    cam_t1 = Camera(look_at([0, 0, 0], [np.sin(theta), 0, np.cos(theta)]), 60.0)  # pans to the left
    positions, f = _plane_positions(cam_t, width, height, 3.0)
    flow = motion_vectors(positions, cam_t, cam_t1, width, height)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    a, b = (u - width / 2) / f, (v - height / 2) / f  # right and down, per unit depth
    denom = np.cos(theta) - a * np.sin(theta)
    np.testing.assert_allclose(flow[..., 0], width / 2 + f * (a * np.cos(theta) + np.sin(theta)) / denom - u)
    np.testing.assert_allclose(flow[..., 1], height / 2 + f * b / denom - v)
    assert (flow[..., 0] > 0).all()  # panning left moves the whole image right


def test_motion_vectors_are_nan_without_a_surface_or_behind_the_camera():
    from src.render.volume_camera import Camera, look_at, motion_vectors

    cam = Camera(look_at([0, 0, 0], [0, 0, 1]), 45.0)
    positions, _ = _plane_positions(cam, 4, 3, 2.0)
    positions[0, 0] = np.inf  # sky
    positions[1, 1] = [0.0, 0.0, -1.0]  # behind
    flow = motion_vectors(positions, cam, cam, 4, 3)
    assert np.isnan(flow[0, 0]).all() and np.isnan(flow[1, 1]).all()
    finite = np.isfinite(flow).all(-1)
    assert finite.sum() == 10 and np.abs(flow[finite]).max() < 1e-9  # a still camera: no motion
    with pytest.raises(ValueError, match="world_positions_t"):
        motion_vectors(positions[:2], cam, cam, 4, 3)


def test_the_camera_path_is_smooth(mitsuba_variant, ds):
    from src.render.volume_scenes import camera_at

    origins = np.array([camera_at("godrays", 2, f, ds).origin for f in np.linspace(0, ds["frames"] - 1, 29)])
    steps = np.linalg.norm(np.diff(origins, axis=0), axis=1)
    assert steps.max() < 0.1 and steps.max() < 1.5 * steps.min() + 1e-6  # small, even steps
