"""Procedural density and albedo grids of heterogeneous media, in numpy, for the volumetric scene family.

Every function is pure and vectorised over points (the only Python loops run over octaves, lattice
corners or the 27 neighbouring Worley cells, never over voxels). Noise lattices are *periodic* tables
drawn once from a seeded generator, so a noise field is defined on all of space: translating the domain
by a wind velocity per frame (advection) or moving along a 4th, time axis (evolution) changes a frame
smoothly and never needs re-normalising. Values stay in [0, 1] by construction (value noise and fBm are
convex combinations of lattice values in [0, 1]), not by a per-grid min-max that would flicker in time.

Grid layout: a grid is a numpy array indexed ``[z, y, x]`` (plus a channel axis for albedo), the layout
``mi.VolumeGrid`` expects; voxel centres sit at ``(i + 0.5) / n`` of the unit cube that a ``gridvolume``'s
``to_world`` maps onto the medium's box (``box_to_world``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

#: Lattice cells per axis of a periodic noise table: a field repeats every ``LATTICE_PERIOD`` feature sizes.
LATTICE_PERIOD = 16


@dataclass(frozen=True)
class Box:
    """An axis-aligned box: ``centre`` and full edge lengths ``size`` (scene units)."""

    centre: tuple[float, float, float]
    size: tuple[float, float, float]

    @property
    def lower(self) -> np.ndarray:
        return np.asarray(self.centre, float) - 0.5 * np.asarray(self.size, float)


def grid_shape(box: Box, grid_res: int) -> tuple[int, int, int]:
    """(nz, ny, nx): ``grid_res`` voxels along the box's longest side, the other sides in proportion (at
    least 4), so voxels are close to cubes."""
    size = np.asarray(box.size, float)
    nx, ny, nz = (max(4, int(round(grid_res * s / size.max()))) for s in size)
    return nz, ny, nx


def voxel_centres(box: Box, shape: tuple[int, int, int]) -> np.ndarray:
    """(nz, ny, nx, 3) world positions (x, y, z) of the voxel centres of a grid of ``shape`` over ``box``."""
    nz, ny, nx = shape
    axes = [(np.arange(n) + 0.5) / n for n in (nx, ny, nz)]
    x, y, z = (box.lower[k] + axes[k] * box.size[k] for k in range(3))
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    return np.stack([xx, yy, zz], -1)


def noise_lattices(rng: np.random.Generator, octaves: int, dims: int = 4) -> np.ndarray:
    """(octaves, LATTICE_PERIOD ** dims) uniform [0, 1) tables, one per fBm octave."""
    return rng.random((octaves, LATTICE_PERIOD**dims))


def _fade(t: np.ndarray) -> np.ndarray:
    """Perlin's quintic fade 6t^5 - 15t^4 + 10t^3: C2 across lattice cells."""
    return t * t * t * (t * (6 * t - 15) + 10)


def value_noise_nd(points: np.ndarray, lattice: np.ndarray) -> np.ndarray:
    """Value noise at ``points`` (..., d) in lattice units: the periodic table ``lattice`` (P ** d values,
    P = LATTICE_PERIOD) interpolated with the quintic fade over the 2 ** d corners of each cell. Equals the
    table at integer points; a convex combination of table values (so in [0, 1]) elsewhere."""
    d = points.shape[-1]
    base = np.floor(points)
    frac = _fade(points - base)
    cell = base.astype(np.int64) % LATTICE_PERIOD
    strides = LATTICE_PERIOD ** np.arange(d)
    out = np.zeros(points.shape[:-1])
    for corner in range(2**d):
        bits = np.array([(corner >> k) & 1 for k in range(d)])
        idx = ((cell + bits) % LATTICE_PERIOD) @ strides
        weight = np.prod(np.where(bits, frac, 1 - frac), axis=-1)
        out += weight * lattice[idx]
    return out


def fbm(
    points: np.ndarray,
    lattices: np.ndarray,
    persistence: float,
    lacunarity: float = 2.0,
    time: float = 0.0,
) -> np.ndarray:
    """Fractal Brownian motion in [0, 1] at ``points`` (..., 3) in units of the base feature size: the
    value noise of each octave o (``lattices[o]``, 4-D: x, y, z and ``time``) at frequency
    ``lacunarity ** o`` with amplitude ``persistence ** o``, divided by the sum of the amplitudes."""
    pts4 = np.concatenate([points, np.full(points.shape[:-1] + (1,), float(time))], -1)
    out = np.zeros(points.shape[:-1])
    total = 0.0
    for o, lattice in enumerate(lattices):
        amp, freq = persistence**o, lacunarity**o
        # A fixed per-octave shift keeps the octaves' lattice points from lining up at the origin.
        out += amp * value_noise_nd(pts4 * freq + 0.37 * o, lattice)
        total += amp
    return out / total


def worley_points(rng: np.random.Generator, cells: int) -> np.ndarray:
    """(cells, cells, cells, 3) feature points: one uniform point per cell of a periodic ``cells`` ** 3
    grid, as offsets in [0, 1) within its cell (indexed [x, y, z])."""
    return rng.random((cells, cells, cells, 3))


def worley(points: np.ndarray, features: np.ndarray) -> np.ndarray:
    """Worley (cellular) noise F1 at ``points`` (..., 3) in cell units: the distance to the nearest feature
    point of the periodic grid ``features`` (from ``worley_points``), searching the 27 neighbouring cells
    (exact: one point per cell is never farther than a neighbouring cell's). 0 at a feature point."""
    cells = features.shape[0]
    base = np.floor(points).astype(np.int64)
    best = np.full(points.shape[:-1], np.inf)
    for offset in np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3):
        cell = base + offset
        wrapped = cell % cells
        feature = cell + features[wrapped[..., 0], wrapped[..., 1], wrapped[..., 2]]
        best = np.minimum(best, np.linalg.norm(points - feature, axis=-1))
    return best


def smoothstep(lo: float, hi: float, x: np.ndarray) -> np.ndarray:
    """0 below ``lo``, 1 above ``hi``, Hermite 3t^2 - 2t^3 between."""
    t = np.clip((x - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def cloud_density(
    local: np.ndarray,
    shape_noise: np.ndarray,
    billows: np.ndarray,
    coverage: float,
    softness: float,
) -> np.ndarray:
    """A cumulus-like cloud in [0, 1]: an ellipsoidal envelope over the box (``local`` in [-1, 1]^3, its
    base flattened below the centre) eroded by fBm ``shape_noise`` and billowed by inverted Worley noise
    ``billows`` (both in [0, 1]); ``coverage`` shifts the threshold (more cloud), ``softness`` widens its
    edge."""
    r2 = (
        local[..., 0] ** 2 + (local[..., 1] * np.where(local[..., 1] < 0, 1.6, 1.0)) ** 2 + local[..., 2] ** 2
    )
    envelope = np.clip(1.0 - r2, 0.0, 1.0)
    field = envelope * (0.55 * shape_noise + 0.45 * billows) + coverage - 0.5
    return smoothstep(0.25, 0.25 + softness, field)


def plume_density(
    local: np.ndarray,
    noise: np.ndarray,
    radius: float,
    spread: float,
    sway: np.ndarray,
    detail: float,
) -> np.ndarray:
    """A rising smoke column in [0, 1]: ``local`` in [-1, 1]^3 of the box, height h = (y + 1) / 2 in
    [0, 1]; a Gaussian cross-section of radius ``radius + spread * h`` (box half-widths) around a centre
    line displaced by ``sway`` (..., 2: x and z offsets per point), faded in at the source and out at the
    top, and broken up by ``noise`` in [0, 1] with strength ``detail``."""
    h = 0.5 * (local[..., 1] + 1.0)
    dx, dz = local[..., 0] - sway[..., 0], local[..., 2] - sway[..., 1]
    r = radius + spread * h
    column = np.exp(-(dx * dx + dz * dz) / (r * r))
    fade = smoothstep(0.0, 0.08, h) * (1.0 - smoothstep(0.6, 1.0, h))
    return np.clip(column * fade * (1.0 - detail + detail * noise), 0.0, 1.0)


def height_fog_density(
    height: np.ndarray, scale_height: float, noise: np.ndarray, modulation: float
) -> np.ndarray:
    """Exponential height fog in [0, 1]: exp(-h / ``scale_height``) for ``height`` h >= 0 above the fog's
    base, times (1 - ``modulation`` + ``modulation`` * ``noise``); ``modulation`` = 0: the closed form."""
    h = np.maximum(height, 0.0)
    return np.exp(-h / scale_height) * (1.0 - modulation + modulation * noise)


def haze_density(noise: np.ndarray, modulation: float) -> np.ndarray:
    """Nearly uniform haze in [0, 1] (god rays need scattering everywhere the sun's shafts pass):
    1 - ``modulation`` + ``modulation`` * ``noise``."""
    return 1.0 - modulation + modulation * noise


def albedo_grid(noise: np.ndarray, low: Sequence[float], high: Sequence[float]) -> np.ndarray:
    """(..., 3) single-scattering albedo varying in space: the RGB colours ``low`` and ``high`` mixed by
    ``noise`` in [0, 1] (in [0, 1] when both colours are)."""
    t = noise[..., None]
    return np.asarray(low, float) * (1 - t) + np.asarray(high, float) * t


def box_to_world(box: Box) -> np.ndarray:
    """The 4x4 matrix taking a ``gridvolume``'s unit cube [0, 1]^3 onto ``box``."""
    m = np.diag([*box.size, 1.0])
    m[:3, 3] = box.lower
    return m
