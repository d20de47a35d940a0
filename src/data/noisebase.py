"""Noisebase sample sets (Balint et al. 2023, "Neural Partitioning Pyramids for Denoising Monte Carlo
Renderings"; the `noisebase` package 1.1.1): read per-sample frames and make of them the per-pixel
buffers of nrbench's volumetric sequence layout (`src.data.volume_buffers`), which preprocessing turns
into the sequence models' samples (issue 35; the format: docs/noisebase.md).

The package's loaders (`noisebase.loaders.torch.TrainingSampleLoader_v1`, `TestSampleLoader_v1`) are
not used here: they yield one frame's per-sample tensors at a time through a PyTorch DataLoader with
their own shuffling, flips, train/val split and (test) fixed crop, where nrbench needs, for every
`dataset.noisy_spp` count n, the per-pixel mean and variance of the mean of the first n samples, its own
split by sequence, and the forward flow its temporal loss warps with. What they compute is reused: the
RGBE decoding (`noisebase.compression.decompress_RGBE`), the camera basis and view-projection of a
training frame (`noisebase.projective.FlipRotate.apply_camera`, identity orientation) and the projection
to pixels (`noisebase.projective.screen_space_position`). tests/test_noisebase.py checks that the samples
read here equal the package loader's on the same file.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from src.data.volume_aovs import CHANNEL_COUNT, MOMENT_BUFFERS
from src.errors import DataError

FORMATS = ("training", "test")
#: Per-sample arrays: (3 or 4, H, W, S) per frame, and their dtype.
SAMPLE_ARRAYS = {"color": np.uint8, "position": np.float32, "normal": np.float16, "diffuse": np.float16}
#: Per-frame arrays with their per-frame shape ("HW": the frame's height and width) and dtype.
FRAME_ARRAYS: dict[str, tuple[tuple, Any]] = {
    "exposure": ((2,), np.float32),
    "reference": ((3, "H", "W"), np.float32),
    "camera_position": ((3,), np.float32),
    "camera_target": ((3,), np.float32),
    "camera_up": ((3,), np.float32),
    "proj_mat": ((4, 4), np.float32),
    "view_proj_mat": ((4, 4), np.float32),
    "crop_offset": ((2,), np.int32),
}
#: What nrbench reads of a store (the world `motion` is not read: it moves the samples of the *next*
#: frame, see `forward_flow`).
READ_ARRAYS = (*SAMPLE_ARRAYS, *FRAME_ARRAYS)


def open_store(path: Path):
    """The Zarr group of one ZipStore, read-only; a one-line DataError when it is missing or unreadable."""
    import zarr  # lazy: only this kind needs it

    if not path.is_file():
        raise DataError(f"{path}: no such Noisebase ZipStore (dataset.root / dataset.files)")
    try:
        store = zarr.ZipStore(str(path), mode="r")
    except (zipfile.BadZipFile, OSError, ValueError) as e:
        raise DataError(f"{path}: not a readable Zarr ZipStore ({type(e).__name__}: {e})") from None
    try:
        return zarr.group(store=store)
    except Exception as e:  # zarr raises its own errors for a zip that is no Zarr group
        store.close()
        raise DataError(f"{path}: not a Zarr group ({type(e).__name__}: {e})") from None


def _array(group, path: Path, name: str, shape: tuple[int, ...], dtype, index=()) -> np.ndarray:
    """`group[name][index]` after checking the whole array's shape and dtype (one line naming file, array)."""
    if name not in group:
        raise DataError(f"{path}: array {name!r} missing; a Noisebase sample set has {list(READ_ARRAYS)}")
    arr = group[name]
    if tuple(arr.shape) != tuple(shape):
        raise DataError(f"{path}: array {name!r} has shape {tuple(arr.shape)}; expected {tuple(shape)}")
    if arr.dtype != np.dtype(dtype):
        raise DataError(f"{path}: array {name!r} has dtype {arr.dtype}; expected {np.dtype(dtype)}")
    try:
        return np.asarray(arr[index])
    except Exception as e:  # a chunk that does not decompress
        raise DataError(f"{path}: array {name!r} unreadable ({type(e).__name__}: {e})") from None


@dataclass
class Frame:
    """One frame of per-sample data, in a window of the stored frame: `radiance`, `position`, `normal`,
    `diffuse` (C, H, W, S) float32; `reference` (3, H, W); the camera (`camera_position`, `view_proj`
    (4, 4), row vectors) and `offset`, the window's (row, column) in the camera frame of
    `rendering` = (height, width) pixels."""

    radiance: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    diffuse: np.ndarray
    reference: np.ndarray
    camera_position: np.ndarray
    view_proj: np.ndarray
    offset: np.ndarray
    rendering: tuple[int, int]


def _window(crop, height: int, width: int, path: Path) -> tuple[slice, slice]:
    if crop is None:
        return slice(0, height), slice(0, width)
    top, left, h, w = (int(c) for c in crop)
    if top < 0 or left < 0 or h < 1 or w < 1 or top + h > height or left + w > width:
        raise DataError(
            f"{path}: dataset.crop={[top, left, h, w]} ([top, left, height, width]) is not inside its "
            f"{height}x{width} frames"
        )
    return slice(top, top + h), slice(left, left + w)


def read_frames(
    path: Path, fmt: str, frames: list[int], samples: int, crop=None, rendering=(1080, 1920)
) -> list[Frame]:
    """Frames `frames` of one store: a training-format sequence (`fmt="training"`, one store for all
    frames, `rendering` its camera frame) or one test-format frame (`fmt="test"`, `frames` = [0], the
    store the whole camera frame). The first `samples` samples of each pixel, in window `crop`
    ([top, left, height, width] of the stored frame; None: all)."""
    from noisebase.compression import decompress_RGBE
    from noisebase.projective import FlipRotate

    group = open_store(path)
    try:
        if "color" not in group:
            raise DataError(f"{path}: array 'color' missing; a Noisebase sample set has {list(READ_ARRAYS)}")
        colour = group["color"]
        if colour.ndim != (4 if fmt == "test" else 5):
            want = "[4, H, W, S]" if fmt == "test" else "[F, 4, H, W, S]"
            raise DataError(f"{path}: array 'color' has shape {tuple(colour.shape)}; expected {want} ({fmt})")
        n_frames = 1 if fmt == "test" else int(colour.shape[0])
        height, width, stored = (int(s) for s in colour.shape[-3:])
        if samples > stored:
            raise DataError(
                f"{path}: array 'color' has {stored} samples per pixel; the dataset's counts "
                f"(dataset.noisy_spp, dataset.ladder_spp) ask for {samples}"
            )
        missing = [f for f in frames if not 0 <= f < n_frames]
        if missing:
            raise DataError(f"{path}: array 'color' has {n_frames} frames; dataset asks for frames {missing}")
        rows, cols = _window(crop, height, width, path)
        lead = () if fmt == "test" else (n_frames,)
        rendering = (height, width) if fmt == "test" else tuple(int(r) for r in rendering)
        out = []
        for f in frames:
            at = () if fmt == "test" else (f,)
            sample_index = (*at, slice(None), rows, cols, slice(0, samples))
            per_sample = {
                name: _array(
                    group,
                    path,
                    name,
                    (*lead, 4 if name == "color" else 3, height, width, stored),
                    dtype,
                    sample_index,
                )
                for name, dtype in SAMPLE_ARRAYS.items()
            }
            frame_arrays = {
                name: _array(
                    group,
                    path,
                    name,
                    (*lead, *(height if s == "H" else width if s == "W" else s for s in shape)),
                    dtype,
                    at,
                )
                for name, (shape, dtype) in FRAME_ARRAYS.items()
            }
            offset = frame_arrays["crop_offset"].astype(np.int64) + [rows.start, cols.start]
            if fmt == "training":
                # as TrainingSampleDataset: the view-projection rebuilt from proj_mat and the camera vectors
                rotate = FlipRotate(7, rendering[0], rendering[1], height)  # 7: no flip, no rotation
                *_, view_proj = rotate.apply_camera(
                    frame_arrays["camera_target"],
                    frame_arrays["camera_up"],
                    frame_arrays["camera_position"],
                    frame_arrays["proj_mat"],
                    frame_arrays["crop_offset"].copy(),
                )
            else:
                view_proj = frame_arrays["view_proj_mat"]
            out.append(
                Frame(
                    radiance=decompress_RGBE(per_sample["color"], frame_arrays["exposure"]),
                    position=per_sample["position"].astype(np.float32),
                    normal=per_sample["normal"].astype(np.float32),
                    diffuse=per_sample["diffuse"].astype(np.float32),
                    reference=frame_arrays["reference"][:, rows, cols].astype(np.float32),
                    camera_position=frame_arrays["camera_position"].astype(np.float64),
                    view_proj=np.asarray(view_proj, np.float64),
                    offset=offset,
                    rendering=rendering,
                )
            )
        return out
    finally:
        group.store.close()


def finite_samples(samples: np.ndarray) -> np.ndarray:
    """`samples` in float64 with every non-finite value (a sky sample's position, a broken one) as 0: what
    the pixel means of the noisy inputs and of the ladder both average."""
    return np.nan_to_num(samples.astype(np.float64), nan=0.0, posinf=0.0, neginf=0.0)


def pixel_moments(samples: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(C, H, W, S) samples -> the mean of the first `n` per pixel (H, W, C) and the variance of that mean
    (H, W, 1): the unbiased sample variance over the n samples divided by n, averaged over the channels
    (`src.render.moments.variance_of_mean`). Non-finite samples count as 0 (sky positions)."""
    if n < 2:
        raise DataError(f"dataset.noisy_spp: {n} sample(s) per pixel; a variance needs at least 2")
    x = finite_samples(samples[..., :n])
    mean = x.mean(-1)
    var = x.var(-1, ddof=1) / n
    return (
        np.moveaxis(mean, 0, -1).astype(np.float32),
        var.mean(0)[..., None].astype(np.float32),
    )


def ladder_color(frame: Frame, spp: int) -> np.ndarray:
    """One rung of a held-out frame's sample-count ladder (`src.data.ladder`): the (H, W, 3) per-pixel mean
    of the *last* `spp` of the frame's read samples. The noisy inputs take the first n (`pixel_moments`),
    so a rung of k samples shares none of an n-sample input's when n + k <= the samples read (the ladder's
    top count): the noisy inputs' own equivalents are then an independent check, as with a rendered
    ladder. Non-finite samples count as 0, as in `pixel_moments`."""
    stored = frame.radiance.shape[-1]
    if not 1 <= spp <= stored:
        raise DataError(f"dataset.ladder_spp: {spp} samples per pixel; the frames read have {stored}")
    x = finite_samples(frame.radiance[..., stored - spp :])
    return np.moveaxis(x.mean(-1), 0, -1).astype(np.float32)


def forward_flow(mean_position: np.ndarray, frame: Frame, following: Frame | None) -> np.ndarray:
    """(H, W, 2) flow in pixels (+x right, +y down) from `frame` to `following` of each pixel's mean
    world position (H, W, 3), in window coordinates of each frame (their offsets differ: the crops move).
    The convention of `src.render.volume_dataset.frame_motion`: 0 on the last frame (no `following`) and
    where undefined (behind a camera, not finite). Camera motion only: the stored world `motion` is that
    of the following frame's samples, not of this frame's."""
    from noisebase.projective import screen_space_position

    h, w = mean_position.shape[:2]
    if following is None:
        return np.zeros((h, w, 2), np.float32)
    points = np.moveaxis(mean_position.astype(np.float64), -1, 0)[..., None]  # (3, H, W, 1)
    with np.errstate(all="ignore"):
        now = screen_space_position(points, frame.view_proj, *frame.rendering)[..., 0]  # (2, H, W): row, col
        then = screen_space_position(points, following.view_proj, *following.rendering)[..., 0]
        flow_ij = (then - following.offset[:, None, None]) - (now - frame.offset[:, None, None])
    flow = np.stack([flow_ij[1], flow_ij[0]], -1)  # (x, y)
    homogeneous = np.concatenate([points[..., 0], np.ones((1, h, w))])
    w_now = np.einsum("ij,ihw->jhw", frame.view_proj, homogeneous)[3]
    w_then = np.einsum("ij,ihw->jhw", following.view_proj, homogeneous)[3]
    undefined = ~np.isfinite(flow).all(-1) | (w_now <= 0) | (w_then <= 0) | ~np.any(mean_position != 0, -1)
    flow[undefined] = 0.0
    return flow.astype(np.float32)


def volume_frame_buffers(frame: Frame, following: Frame | None, n: int) -> dict[str, np.ndarray]:
    """Every buffer of the volumetric layout (`VOLUME_EXR_BUFFERS`) of one frame from its first `n`
    samples: `color` = `surface` (no media in these scenes; `volume` and the media buffers 0), `albedo`
    (diffuse), `normal`, `position`, `depth` (distance to the camera), each with its variance of the mean;
    `motion` = `forward_flow` of the mean position."""
    h, w = frame.radiance.shape[1:3]
    out = {b: np.zeros((h, w, c), np.float32) for b, c in CHANNEL_COUNT.items()}
    out |= {f"{b}Variance": np.zeros((h, w, 1), np.float32) for b in MOMENT_BUFFERS}
    distance = np.linalg.norm(frame.position - frame.camera_position[:, None, None, None], axis=0)[None]
    for name, samples in (
        ("color", frame.radiance),
        ("albedo", frame.diffuse),
        ("normal", frame.normal),
        ("position", frame.position),
        ("depth", distance),
    ):
        out[name], out[f"{name}Variance"] = pixel_moments(samples, n)
    out["surface"], out["surfaceVariance"] = out["color"], out["colorVariance"]
    out["motion"] = forward_flow(out["position"], frame, following)
    return out


def volume_reference_buffers(frame: Frame, following: Frame | None) -> dict[str, np.ndarray]:
    """The reference file's buffers: the stored clean `reference` as `color` and `surface` (variance 0);
    the other buffers from all the frame's read samples."""
    out = volume_frame_buffers(frame, following, frame.radiance.shape[-1])
    reference = np.moveaxis(frame.reference, 0, -1).astype(np.float32)
    out["color"] = out["surface"] = reference
    out["colorVariance"] = out["surfaceVariance"] = np.zeros_like(out["colorVariance"])
    return out


# --- a set into the volumetric raw layout (`stage=render dataset=noisebase`) -------------------------------

#: The record of what a raw folder was converted from (skips a conversion whose sources are unchanged).
CONVERT_RECORD = "noisebase_convert.json"


def sequence_sources(ds: dict) -> dict[str, list[tuple[Path, int]]]:
    """{scene name: [(store, frame within it) per frame]}: a training set's `scene{index:04d}` sequences
    (one store each, `dataset.sequences` its indices) or a test set's named sequences (a store per frame);
    the first `dataset.frames` frames of each."""
    root, template, frames = Path(ds["root"]), str(ds["files"]), int(ds["frames"])
    out = {}
    for seq in ds["sequences"]:
        if ds["format"] == "training":
            path = root / template.format(index=int(seq))
            out[f"scene{int(seq):04d}"] = [(path, f) for f in range(frames)]
        else:
            out[str(seq)] = [(root / template.format(sequence_name=seq, index=f), 0) for f in range(frames)]
    return out


def source_stamp(paths) -> list:
    """[path, size, mtime] of each store ([path, None] when missing): what says a set's files changed."""
    return [
        [str(p), p.stat().st_size, p.stat().st_mtime_ns] if p.is_file() else [str(p), None] for p in paths
    ]


def convert_to_volume_exrs(ds: dict, raw: Path) -> dict[str, Any]:
    """Every frame of every configured sequence into `raw`: per (scene, frame), one EXR per noisy count
    (`volume_frame_buffers`) and one reference EXR labelled `dataset.reference_spp`
    (`volume_reference_buffers`), named as `src.data.volume_buffers.volume_exr_name`. EXRs of other
    sequences, frames or counts are deleted; nothing is written when the record says the same sources
    and settings made the folder."""
    import json
    import time

    from src.data.volume_buffers import volume_exr_name, write_volume_exr
    from src.io.atomic import atomic_write_json

    sources = sequence_sources(ds)
    noisy = sorted(int(n) for n in ds["noisy_spp"])
    settings = {
        k: ds[k] for k in ("format", "files", "sequences", "frames", "crop", "noisy_spp", "reference_spp")
    }
    settings |= {"rendering": [ds["rendering_height"], ds["rendering_width"]]}
    stores = sorted({p for frames in sources.values() for p, _ in frames})
    record = {"settings": settings, "sources": source_stamp(stores)}
    wanted = {
        volume_exr_name(scene, f, n)
        for scene, frames in sources.items()
        for f in range(len(frames))
        for n in (*noisy, int(ds["reference_spp"]))
    }
    raw.mkdir(parents=True, exist_ok=True)
    record_path = raw / CONVERT_RECORD
    have = {p.name for p in raw.glob("*.exr")}
    try:
        same = json.loads(record_path.read_text()) == record
    except (OSError, ValueError):
        same = False
    if same and wanted <= have:
        return {"files_written": 0, "files_cached": len(wanted), "seconds": 0.0, "sequences": len(sources)}
    start = time.perf_counter()
    record_path.unlink(missing_ok=True)  # written again only when every file is: a failure converts again
    for name in have - wanted:
        (raw / name).unlink()
    crop, rendering = ds.get("crop"), (int(ds["rendering_height"]), int(ds["rendering_width"]))
    for scene, frames in sources.items():
        # two frames in memory at a time (a 1080p test frame at 32 spp is ~3 GB of float32 samples)
        def read(f: int, frames=frames) -> Frame:
            path, index = frames[f]
            return read_frames(path, ds["format"], [index], max(noisy), crop, rendering)[0]

        following = read(0)
        for f in range(len(frames)):
            frame, following = following, (read(f + 1) if f + 1 < len(frames) else None)
            for n in noisy:
                write_volume_exr(
                    raw / volume_exr_name(scene, f, n), volume_frame_buffers(frame, following, n)
                )
            write_volume_exr(
                raw / volume_exr_name(scene, f, int(ds["reference_spp"])),
                volume_reference_buffers(frame, following),
            )
    atomic_write_json(record_path, record)
    return {
        "files_written": len(wanted),
        "files_cached": 0,
        "seconds": time.perf_counter() - start,
        "sequences": len(sources),
    }
