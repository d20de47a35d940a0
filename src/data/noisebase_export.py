"""Write per-sample buffers as Noisebase sample sets (issue 35; docs/noisebase.md), so that methods built
on the `noisebase` package (Balint et al. 2023) train and test on nrbench's renders.

Training format: one Zarr ZipStore per sequence, every array with a leading frame axis; test format: one
store per frame, the same arrays without it. Colour is RGBE-encoded as the package's
`noisebase.compression.compress_RGBE` does it (per-frame exposure range, ceiling exponent, dithered colour
bytes), here with a seeded dither (the package draws from numpy's global generator) and in float64 with
the bytes clipped to 255 (float32 rounding could make the package's dither carry 255 over to 0); normals
and diffuse colour are float16, positions and world motion float32. Arrays are stored as the format page
says: LZ4HC level 9 (Blosc), chunked per frame and per 4 samples.

Cameras (`noisebase_camera`): position, target, up, a DirectX-style projection `proj_mat` and the
view-projection `view_proj_mat` (row vectors), built by the package's own
`noisebase.projective.FlipRotate.apply_camera` as its training loader builds it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from src.errors import DataError

#: Per-sample inputs (C, H, W, S) per frame and the dtype each is stored as (`color`: RGBE uint8).
SAMPLE_DTYPES = {"position": np.float32, "motion": np.float32, "normal": np.float16, "diffuse": np.float16}
#: The camera arrays every frame has.
CAMERA_KEYS = ("camera_position", "camera_target", "camera_up", "proj_mat")
#: The order `FlipRotate.apply_camera` takes them in.
CAMERA_ORDER = ("camera_target", "camera_up", "camera_position", "proj_mat")
#: Near and far planes of the projection (the package's example matrix: 0.1 and 1000).
NEAR, FAR = 0.1, 1000.0


def encode_rgbe(color: np.ndarray, uniform: Callable[[tuple], np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(3, H, W, S) radiance -> (4, H, W, S) uint8 RGBE and the exposure [min, max] float32: the exponent
    byte `e = min(floor((log max(r, g, b) - min) / (max - min) * 256), 255)` (0 for black samples), the
    colour bytes `floor(c / E * 255)` plus 1 where the fraction exceeds `uniform(shape)` (unbiased), with
    `E = exp((e + 1) / 256 * (max - min) + min)` (>= the brightest channel: no byte exceeds 255).
    A frame whose positive values are all one value gets the range [v, v + 1e-6] (the package divides by
    zero there); an all-black frame is all zero bytes with exposure [0, 0], as the package's."""
    color = np.asarray(color, np.float64)
    if not np.isfinite(color).all() or (color < 0).any():
        raise DataError("noisebase export: radiance must be finite and non-negative to be RGBE-encoded")
    positive = color[color > 0]
    if positive.size == 0:
        return np.zeros((4, *color.shape[1:]), np.uint8), np.zeros(2, np.float32)
    lo, hi = float(np.log(positive.min())), float(np.log(positive.max()))
    hi = max(hi, lo + 1e-6)
    brightest = color.max(0)
    lit = brightest > 0
    exponent = np.log(np.where(lit, brightest, 1.0))
    e = np.where(lit, np.minimum(np.floor((exponent - lo) / (hi - lo) * 256), 255), 0).astype(np.uint8)
    scale = np.exp((e.astype(np.float64) + 1) / 256 * (hi - lo) + lo)
    rgb_float = color / scale * 255
    rgb = np.floor(rgb_float)
    rgb = np.minimum(rgb + ((rgb_float - rgb) > uniform(rgb.shape)), 255).astype(np.uint8)
    return np.concatenate([rgb, e[None]]), np.array([lo, hi], np.float32)


def projection_matrix(fov_x_deg: float, width: int, height: int) -> np.ndarray:
    """The DirectX-style perspective matrix of the package's example (column form: clip = P @ [x, y, z, 1]
    in camera space x right, y up, z forward; w = z): a horizontal field of view `fov_x_deg`."""
    sx = 1 / np.tan(np.radians(fov_x_deg) / 2)
    return np.array(
        [
            [sx, 0, 0, 0],
            [0, sx * width / height, 0, 0],
            [0, 0, FAR / (FAR - NEAR), -NEAR * FAR / (FAR - NEAR)],
            [0, 0, 1, 0],
        ],
        np.float32,
    )


def view_projection(camera: Mapping[str, np.ndarray], rendering: tuple[int, int], window: int) -> np.ndarray:
    """`view_proj_mat` (row vectors) of one frame's camera, as the package's training loader builds it."""
    from noisebase.projective import FlipRotate

    rotate = FlipRotate(7, rendering[0], rendering[1], window)  # 7: the identity orientation
    # float32 in, as the loader reads them from the store: the same rounding, the same matrix
    *_, pv = rotate.apply_camera(
        *(np.asarray(camera[k], np.float32) for k in CAMERA_ORDER), np.zeros(2, np.int32)
    )
    return np.asarray(pv, np.float32)


def frame_arrays(
    samples: Mapping[str, np.ndarray],
    reference: np.ndarray,
    camera: Mapping[str, np.ndarray],
    crop_offset,
    rendering: tuple[int, int],
    uniform: Callable[[tuple], np.ndarray],
) -> dict[str, np.ndarray]:
    """The arrays of one frame in the format: `samples` holds `radiance` and `SAMPLE_DTYPES`' buffers
    (C, H, W, S); `reference` (3, H, W); `camera` the `CAMERA_KEYS`; `crop_offset` (row, column) of the
    frame in its `rendering` (height, width) camera frame."""
    radiance = np.asarray(samples["radiance"])
    if radiance.ndim != 4 or radiance.shape[0] != 3:
        raise DataError(f"noisebase export: radiance has shape {radiance.shape}; expected (3, H, W, S)")
    shape = radiance.shape
    color, exposure = encode_rgbe(radiance, uniform)
    out = {"color": color, "exposure": exposure}
    for name, dtype in SAMPLE_DTYPES.items():
        value = np.asarray(samples[name])
        if value.shape != shape:
            raise DataError(
                f"noisebase export: {name} has shape {value.shape}; expected {shape} (radiance's)"
            )
        out[name] = value.astype(dtype)
    out["reference"] = np.asarray(reference, np.float32)
    if out["reference"].shape != shape[:3]:
        raise DataError(
            f"noisebase export: reference has shape {out['reference'].shape}; expected {shape[:3]}"
        )
    out |= {k: np.asarray(camera[k], np.float32) for k in CAMERA_KEYS}
    out["view_proj_mat"] = view_projection(out, rendering, shape[1])  # from the stored float32 camera
    out["crop_offset"] = np.asarray(crop_offset, np.int32)
    return out


def write_store(path: Path, arrays: Mapping[str, np.ndarray], frame_axis: bool) -> Path:
    """One ZipStore of `arrays` (LZ4HC 9; per-sample arrays chunked per frame and per 4 samples), written
    to a temporary name and renamed (a crash leaves no half store under the final name)."""
    import zarr
    from numcodecs import Blosc

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".part")
    tmp.unlink(missing_ok=True)
    store = zarr.ZipStore(str(tmp), mode="w")
    try:
        group = zarr.group(store=store)
        codec = Blosc(cname="lz4hc", clevel=9, shuffle=Blosc.SHUFFLE)
        for name, value in arrays.items():
            chunks = list(value.shape)
            if frame_axis:
                chunks[0] = 1
            if value.ndim == (5 if frame_axis else 4):
                chunks[-1] = 4
            group.create_dataset(name, data=value, chunks=tuple(chunks), compressor=codec)
    finally:
        store.close()
    tmp.replace(path)
    return path


def write_training_sequence(path: Path, frames: list[dict[str, np.ndarray]]) -> Path:
    """A training-format store of the `frame_arrays` of every frame (stacked on a leading frame axis)."""
    return write_store(path, {k: np.stack([f[k] for f in frames]) for k in frames[0]}, frame_axis=True)


def write_test_frame(path: Path, frame: dict[str, np.ndarray]) -> Path:
    """A test-format store: one frame's `frame_arrays`."""
    return write_store(path, frame, frame_axis=False)
