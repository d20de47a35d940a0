"""The procedural media grids (src/render/volume_grids.py) by value: each density, noise and layout
function at chosen points against its closed form written out here, with lattices and parameters where
a changed constant, axis or weight changes the answer (the mutation group `moments` runs this file;
tests/test_volume_scenes.py keeps the range, spectrum and brute-force Worley checks)."""

import numpy as np
import pytest

from src.render import volume_grids as vg

P = vg.LATTICE_PERIOD


def fade(t):
    return 6 * t**5 - 15 * t**4 + 10 * t**3


def test_value_noise_between_lattice_points_is_the_faded_multilinear_blend():
    """3-D value noise at a point with distinct fractions per axis: sum over the 8 corners of the table
    value times prod_k (fade(f_k) or 1 - fade(f_k)), the table indexed x + P y + P^2 z (periodic)."""
    lattice = np.random.default_rng(2).random(P**3)
    point = np.array([[P - 1 + 0.2, 3.7, 30.45]])  # x wraps to 0 at the upper corner, z wraps past P
    base, frac = np.array([P - 1, 3, 30]), np.array([0.2, 0.7, 0.45])
    expected = 0.0
    for corner in np.ndindex(2, 2, 2):
        c = (base + corner) % P
        w = np.prod([fade(f) if b else 1 - fade(f) for b, f in zip(corner, frac, strict=True)])
        expected += w * lattice[c[0] + P * c[1] + P * P * c[2]]
    assert vg.value_noise_nd(point, lattice)[0] == pytest.approx(expected, rel=1e-12)
    # 1-D, a quarter of the way: fade(0.25) = 0.103515625 of the next value.
    line = np.random.default_rng(3).random(P)
    got = vg.value_noise_nd(np.array([[5.25], [-0.75]]), line)
    assert got[0] == pytest.approx(line[5] + 0.103515625 * (line[6] - line[5]), rel=1e-12)
    assert got[1] == pytest.approx(line[P - 1] + 0.103515625 * (line[0] - line[P - 1]), rel=1e-12)


@pytest.mark.parametrize("lacunarity", [None, 3.0])
def test_fbm_weights_octaves_by_persistence_at_lacunarity_frequencies(lacunarity):
    """Octave o reads its own table at p * lacunarity^o + 0.37 o (x, y, z and the time axis; lacunarity
    2 by default) with weight persistence^o, normalised by the sum of the weights. Octaves 0 and 2 have
    constant tables, and the points and time are chosen so that octave 1 lands on lattice points (its
    value there is the table entry)."""
    lac = 2.0 if lacunarity is None else lacunarity
    persistence, time = 0.6, (7 - 0.37) / lac
    lattices = np.random.default_rng(4).random((3, P**4))
    lattices[0], lattices[2] = 0.25, 0.8
    k = np.array([[2, 5, 11], [14, 0, 3]])
    points = (k - 0.37) / lac
    kwargs = {} if lacunarity is None else {"lacunarity": lacunarity}
    got = vg.fbm(points, lattices, persistence, time=time, **kwargs)
    k4 = np.concatenate([k, np.full((2, 1), 7)], -1) % P
    octave1 = lattices[1][k4 @ P ** np.arange(4)]
    weights = np.array([1, persistence, persistence**2])
    expected = (weights[0] * 0.25 + weights[1] * octave1 + weights[2] * 0.8) / weights.sum()
    np.testing.assert_allclose(got, expected, rtol=1e-12)


def test_smoothstep_closed_form():
    x = np.array([-1.0, 0.2, 0.3, 0.4, 0.55, 0.6, 2.0])
    t = np.clip((x - 0.2) / 0.4, 0, 1)
    np.testing.assert_allclose(vg.smoothstep(0.2, 0.6, x), 3 * t**2 - 2 * t**3, rtol=1e-12)
    assert vg.smoothstep(0.2, 0.6, np.array([0.3]))[0] == pytest.approx(0.15625)
    # lo == hi: a step at lo (no division by zero).
    np.testing.assert_array_equal(vg.smoothstep(0.5, 0.5, np.array([0.4, 0.5, 0.6])), [0.0, 0.0, 1.0])


def test_cloud_density_closed_form():
    """Envelope 1 - (x^2 + (1.6 y)^2 + z^2) below the centre (y < 0), 1 - |local|^2 above; field =
    envelope (0.55 shape + 0.45 billows) + coverage - 0.5; density smoothstep(0.25, 0.25 + softness)."""
    local = np.array([[0.1, -0.4, 0.2], [0.1, 0.4, 0.2], [0.0, 0.0, 0.0], [0.9, -0.9, 0.0]])
    shape, billows = np.array([0.9, 0.9, 0.6, 1.0]), np.array([0.5, 0.5, 0.4, 1.0])
    coverage, softness = 0.4, 0.3
    r2 = local[:, 0] ** 2 + (local[:, 1] * np.where(local[:, 1] < 0, 1.6, 1.0)) ** 2 + local[:, 2] ** 2
    field = np.clip(1 - r2, 0, 1) * (0.55 * shape + 0.45 * billows) + coverage - 0.5
    t = np.clip((field - 0.25) / softness, 0, 1)
    got = vg.cloud_density(local, shape, billows, coverage, softness)
    np.testing.assert_allclose(got, 3 * t**2 - 2 * t**3, rtol=1e-12)
    assert 0 < got[0] < got[1] < 1  # the flattened base is thinner than the same point above the centre
    assert 0 < got[2] < 1 and got[3] == 0.0  # outside the envelope: coverage - 0.5 < 0.25
    # High coverage: outside the envelope (r^2 > 1) the envelope is 0, not negative, so the field is
    # coverage - 0.5 = 0.4 there: smoothstep at t = 0.5, density 0.5.
    outside = np.array([[0.9, -0.9, 0.5], [1.0, 1.0, 1.0]])
    assert vg.cloud_density(outside, np.ones(2), np.ones(2), 0.9, 0.3).tolist() == pytest.approx([0.5, 0.5])


def test_plume_density_closed_form():
    """h = (y + 1) / 2; a Gaussian exp(-(dx^2 + dz^2) / r^2), r = radius + spread h, around the swayed
    centre; faded in by smoothstep(0, 0.08, h) and out by 1 - smoothstep(0.6, 1, h); times
    1 - detail + detail * noise."""
    local = np.array([[0.1, -0.5, -0.2], [0.3, 0.4, 0.1], [0.0, -0.95, 0.0], [0.0, 0.9, 0.0]])
    sway = np.array([[0.05, -0.1], [0.2, 0.0], [0.0, 0.0], [0.0, 0.0]])
    noise = np.array([0.3, 0.8, 1.0, 1.0])
    radius, spread, detail = 0.12, 0.35, 0.7
    h = (local[:, 1] + 1) / 2
    r = radius + spread * h
    column = np.exp(-((local[:, 0] - sway[:, 0]) ** 2 + (local[:, 2] - sway[:, 1]) ** 2) / r**2)

    def step(lo, hi, x):
        t = np.clip((x - lo) / (hi - lo), 0, 1)
        return 3 * t**2 - 2 * t**3

    expected = column * step(0, 0.08, h) * (1 - step(0.6, 1, h)) * (1 - detail + detail * noise)
    got = vg.plume_density(local, noise, radius, spread, sway, detail)
    np.testing.assert_allclose(got, expected, rtol=1e-12)
    assert 0 < got[2] < 1 and 0 < got[3] < 1  # faded at the source and near the top


def test_height_fog_haze_and_albedo_closed_forms():
    h = np.array([-0.5, 0.0, 0.35, 1.4])
    noise = np.array([0.2, 0.9, 0.5, 0.0])
    fog = vg.height_fog_density(h, 0.7, noise, 0.4)
    np.testing.assert_allclose(fog, np.exp(-np.maximum(h, 0) / 0.7) * (0.6 + 0.4 * noise), rtol=1e-12)
    assert fog[0] == pytest.approx(0.6 + 0.4 * 0.2)  # below the base: the base density
    np.testing.assert_allclose(vg.haze_density(noise, 0.3), 0.7 + 0.3 * noise, rtol=1e-12)
    albedo = vg.albedo_grid(np.array([0.0, 0.25, 1.0]), [0.2, 0.4, 0.6], [1.0, 0.8, 0.6])
    np.testing.assert_allclose(albedo, [[0.2, 0.4, 0.6], [0.4, 0.5, 0.6], [1.0, 0.8, 0.6]], rtol=1e-12)


def test_grid_layout_closed_forms():
    """grid_shape: `grid_res` voxels along the longest side, the others rounded in proportion, at least
    4; voxel centres lower + (i + 0.5) / n * size per axis, indexed [z, y, x]; box_to_world maps the
    unit cube's corners onto the box's."""
    box = vg.Box((1.0, -2.0, 0.5), (10.0, 3.0, 1.0))
    assert box.lower.tolist() == [-4.0, -3.5, 0.0]
    assert vg.grid_shape(box, 20) == (4, 6, 20)  # z: 2 -> at least 4; y: 6; x: 20
    assert vg.grid_shape(vg.Box((0, 0, 0), (2.0, 7.0, 3.5)), 8) == (4, 8, 4)
    assert vg.grid_shape(vg.Box((0, 0, 0), (9.0, 9.0, 5.0)), 9) == (5, 9, 9)
    centres = vg.voxel_centres(box, (4, 6, 20))
    assert centres.shape == (4, 6, 20, 3)
    np.testing.assert_allclose(centres[0, 0, 0], [-4 + 0.25, -3.5 + 0.25, 0.125])
    np.testing.assert_allclose(centres[3, 5, 19], [6 - 0.25, -0.5 - 0.25, 1 - 0.125])
    np.testing.assert_allclose(centres[1, 2, 3], [-4 + 3.5 * 0.5, -3.5 + 2.5 * 0.5, 1.5 * 0.25])
    m = vg.box_to_world(box)
    np.testing.assert_allclose(m @ [0, 0, 0, 1], [-4.0, -3.5, 0.0, 1.0])
    np.testing.assert_allclose(m @ [1, 1, 1, 1], [6.0, -0.5, 1.0, 1.0])
    np.testing.assert_allclose(m[3], [0, 0, 0, 1])


def test_lattices_and_feature_points_come_from_the_generator():
    lattices = vg.noise_lattices(np.random.default_rng(9), 3, dims=2)
    np.testing.assert_array_equal(lattices, np.random.default_rng(9).random((3, P**2)))
    assert vg.noise_lattices(np.random.default_rng(9), 2).shape == (2, P**4)
    features = vg.worley_points(np.random.default_rng(9), 5)
    np.testing.assert_array_equal(features, np.random.default_rng(9).random((5, 5, 5, 3)))


def test_worley_at_hand_placed_feature_points():
    """Feature points at the cell centres of a 2-cell periodic grid: F1 is the distance to the nearest
    centre, periodic images included (x = 3.7 is 0.2 from the centre 3.5 of the image of cell 1)."""
    features = np.full((2, 2, 2, 3), 0.5)
    points = np.array(
        [[0.5, 0.5, 0.5], [0.1, 0.5, 0.5], [1.0, 1.0, 1.0], [0.05, 0.05, 0.05], [3.7, 0.5, 1.5]]
    )
    expected = [0.0, 0.4, np.sqrt(3 * 0.25), np.sqrt(3) * 0.45, 0.2]
    np.testing.assert_allclose(vg.worley(points, features), expected, rtol=1e-12)


def test_default_time_is_the_zero_slice():
    """Without `time` the fourth lattice axis is read at 0: octave 0 (random table) at integer points
    returns the entries with time index 0; octaves 1 and 2 are constant."""
    lattices = np.random.default_rng(6).random((3, P**4))
    lattices[1], lattices[2] = 0.5, 0.1
    k = np.array([[1, 2, 3], [15, 0, 7]])
    expected = (lattices[0][k @ P ** np.arange(3)] + 0.5 * 0.5 + 0.25 * 0.1) / 1.75
    np.testing.assert_allclose(vg.fbm(k.astype(float), lattices, 0.5), expected, rtol=1e-12)


def test_grid_shaped_points_give_the_values_of_the_flat_points():
    """The scenes evaluate the noises on (nz, ny, nx, 3) voxel-centre arrays: each function on such an
    array (unequal axes) equals the same points flattened to (N, 3), reshaped, and has the grid's shape."""
    rng = np.random.default_rng(8)
    grid = rng.uniform(0, 20, (2, 4, 5, 3))  # shape[1] != 3, shape[0] != shape[2]
    flat = grid.reshape(-1, 3)
    lattice3, lattices4 = rng.random(P**3), rng.random((2, P**4))
    features = vg.worley_points(rng, 4)
    for name, fn in [
        ("value noise", lambda p: vg.value_noise_nd(p, lattice3)),
        ("fbm", lambda p: vg.fbm(p, lattices4, 0.5, time=0.3)),
        ("worley", lambda p: vg.worley(p, features)),
    ]:
        got = fn(grid)
        assert got.shape == (2, 4, 5), name
        np.testing.assert_allclose(got.reshape(-1), fn(flat), rtol=1e-12, err_msg=name)


# Surviving mutants of src/render/volume_grids.py (bash scripts/mutation.sh moments), all equivalent here:
# - albedo_grid `np.asarray(low / high, float)` -> dtype None or dropped (4), grid_shape
#   `np.asarray(box.size, float)` -> dtype None or dropped (2): float lists stay float64, and integer
#   ones (int64) are multiplied by float noise / divided, giving the same float values.
# - cloud_density `local[..., 1] < 0` -> `<= 0`: at y = 0 the flattening factor multiplies 0.
# - cloud_density envelope `np.clip(1 - r2, 0.0, 1.0)` -> upper bound None or 2.0: r2 >= 0, so 1 - r2 <= 1.
# - plume_density `np.clip(..., 0.0, 1.0)` -> lower bound None, upper None or 2.0: the product of a
#   Gaussian, two smoothsteps and 1 - detail + detail * noise lies in [0, 1] for detail and noise in
#   [0, 1] (as the scenes draw them), so the clip never acts.
# - worley: `features.shape[1]` for `shape[0]` (feature grids are cubic, `worley_points`); the 27 offsets
#   built with meshgrid's default "xy" indexing, from 4 copies of [-1, 0, 1] (a superset of the same 27
#   offsets), reshaped with -2 (numpy reads any negative size as "infer"), or subtracted from the base
#   cell instead of added (the offset set is symmetric): each searches the same neighbouring cells.
