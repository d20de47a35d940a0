"""Blender synthetic (nerf_synthetic) scenes: loading one split's cameras and images.

Format (Mildenhall et al. 2020): ``<scene>/transforms_{train,val,test}.json`` with

    {"camera_angle_x": <horizontal field of view, radians>,
     "frames": [{"file_path": "./train/r_0", "transform_matrix": <4x4 camera-to-world>}, ...]}

and RGBA PNGs with *straight* (non-premultiplied) alpha. ``file_path`` is relative to the scene folder
and usually has no extension (".png" is appended when the path as written is not a file). The camera
convention and the rays through the pixels are in ``src.data.rays``; random training batches of rays in
``src.data.ray_batches``.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from src.data.rays import focal_from_fov
from src.data.rgba import downscale_rgba, read_rgba
from src.errors import ConfigError, DataError

#: Largest |R^T R - I| entry (and |det R - 1|) accepted for the rotation part of a transform_matrix.
ROTATION_TOLERANCE = 1e-3
#: Largest deviation of a transform_matrix bottom row from [0, 0, 0, 1].
BOTTOM_ROW_TOLERANCE = 1e-4


@dataclass
class BlenderSplit:
    """One split of a Blender-format scene, composited on ``background``.

    ``images`` (N, H, W, 3) float32 in [0, 1]: rgb * alpha + background * (1 - alpha), computed on the
    8-bit values / 255 (the PNG's sRGB-encoded colour, as NeRF does). ``alphas`` (N, H, W) float32.
    ``c2w`` (N, 4, 4) float32 OpenGL camera-to-world. ``focal`` in pixels of the (downscaled) images.
    """

    images: np.ndarray
    alphas: np.ndarray
    c2w: np.ndarray
    focal: float
    width: int
    height: int
    names: list[str]
    camera_angle_x: float
    files: list[Path] = field(default_factory=list)


def _read_transforms(path: Path) -> dict:
    if not path.is_file():
        raise DataError(f"{path}: transforms file not found; expected a JSON file in the Blender format")
    try:
        meta = json.loads(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError as err:
        raise DataError(f"{path}: not UTF-8 text ({err.reason}); expected a JSON file") from err
    except json.JSONDecodeError as err:
        raise DataError(
            f"{path}: malformed JSON at line {err.lineno} column {err.colno} ({err.msg})"
        ) from err
    if not isinstance(meta, dict):
        raise DataError(f"{path}: top level is a {type(meta).__name__}; expected a JSON object")
    for key in ("camera_angle_x", "frames"):
        if key not in meta:
            raise DataError(f"{path}: missing key '{key}'; found keys {sorted(meta)}")
    angle = meta["camera_angle_x"]
    if isinstance(angle, bool) or not isinstance(angle, int | float) or not 0.0 < angle < math.pi:
        raise DataError(
            f"{path}: camera_angle_x is {angle!r}; expected a horizontal field of view in radians in (0, pi)"
        )
    frames = meta["frames"]
    if not isinstance(frames, list) or not frames:
        raise DataError(
            f"{path}: 'frames' is {type(frames).__name__} of length "
            f"{len(frames) if hasattr(frames, '__len__') else '?'}; expected a non-empty list"
        )
    return meta


def _check_matrix(path: Path, index: int, value) -> np.ndarray:
    where = f"{path}: frames[{index}].transform_matrix"
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise DataError(f"{where} is not an array of numbers ({err}); expected a 4x4 matrix") from err
    if m.shape != (4, 4):
        raise DataError(f"{where} has shape {m.shape}; expected (4, 4)")
    if not np.isfinite(m).all():
        raise DataError(f"{where} has NaN/Inf entries; expected a finite 4x4 camera-to-world matrix")
    bottom = np.abs(m[3] - [0.0, 0.0, 0.0, 1.0]).max()
    if bottom > BOTTOM_ROW_TOLERANCE:
        raise DataError(f"{where} has bottom row {m[3].tolist()}; expected [0, 0, 0, 1]")
    r = m[:3, :3]
    ortho = np.abs(r.T @ r - np.eye(3)).max()
    det = np.linalg.det(r)
    if ortho > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
        raise DataError(
            f"{where}: rotation part is not orthonormal (max |R^T R - I| = {ortho:.3g}, det = {det:.4g}); "
            f"expected a rotation (tolerance {ROTATION_TOLERANCE})"
        )
    return m


def _image_file(scene_dir: Path, transforms: Path, index: int, file_path) -> Path:
    if not isinstance(file_path, str) or not file_path:
        raise DataError(f"{transforms}: frames[{index}].file_path is {file_path!r}; expected a relative path")
    path = scene_dir / file_path
    if path.is_file():
        return path
    with_png = path.with_name(path.name + ".png")
    if with_png.is_file():
        return with_png
    raise DataError(
        f"{transforms}: frames[{index}] image not found: neither {path} nor {with_png.name} exists"
    )


def _check_options(background, downscale, max_images) -> tuple[np.ndarray, int]:
    """``background`` as a float32 RGB array and ``downscale`` as an int, after checking both and
    ``max_images`` (one-line ``ConfigError`` naming the bad argument)."""
    background = np.asarray(background, dtype=np.float32)
    if background.shape != (3,):
        raise ConfigError(f"background: expected 3 values (RGB), got {background.tolist()}")
    if isinstance(downscale, bool) or int(downscale) != downscale or downscale < 1:
        raise ConfigError(f"downscale: expected an integer >= 1, got {downscale!r}")
    downscale = int(downscale)
    if max_images is not None and max_images < 1:
        raise ConfigError(f"max_images: expected an integer >= 1 or null, got {max_images!r}")
    return background, downscale


def _read_frame(scene_dir: Path, transforms: Path, index: int, frame):
    """Frame ``index`` of ``transforms``: its checked camera-to-world, its image file, that image's
    (H, W, 4) RGBA and whether the file has an alpha channel."""
    if not isinstance(frame, dict):
        raise DataError(f"{transforms}: frames[{index}] is a {type(frame).__name__}; expected an object")
    for key in ("file_path", "transform_matrix"):
        if key not in frame:
            raise DataError(f"{transforms}: frames[{index}] is missing key '{key}'; found {sorted(frame)}")
    matrix = _check_matrix(transforms, index, frame["transform_matrix"])
    path = _image_file(scene_dir, transforms, index, frame["file_path"])
    return matrix, path, *read_rgba(path)


#: `alpha` choices: every frame has an alpha channel (rgba), none has (rgb), or all are alike (auto).
ALPHA_POLICIES = ("auto", "rgba", "rgb")


def _check_alpha(path: Path, has_alpha: bool, policy: str, first: tuple[Path, bool] | None):
    """The (path, has_alpha) of the split's first image; every image must have an alpha channel if
    `policy` is rgba, none if rgb, and the same as the first one if auto (a scene mixing the two would be
    composited on the background in some views only)."""
    wanted = {"rgba": True, "rgb": False}.get(policy, has_alpha if first is None else first[1])
    if has_alpha != wanted:
        found = "has an alpha channel" if has_alpha else "has no alpha channel"
        reason = f"like {first[0]}" if policy == "auto" else f"dataset.alpha={policy}"
        raise DataError(f"{path}: image {found}; expected {'RGBA' if wanted else 'RGB'} ({reason})")
    return first or (path, has_alpha)


def _check_size(path: Path, rgba: np.ndarray, first: tuple[Path, tuple[int, int]] | None, downscale: int):
    """The (path, (width, height)) of the split's first image, which every later image must match; the
    first one must be divisible by ``downscale``."""
    size = (rgba.shape[1], rgba.shape[0])
    if first is None:
        if size[0] % downscale or size[1] % downscale:
            raise DataError(
                f"{path}: image is {size[0]}x{size[1]}, not divisible by downscale={downscale}; "
                "expected width and height that are multiples of it"
            )
        return path, size
    if size != first[1]:
        raise DataError(
            f"{path}: image is {size[0]}x{size[1]}; expected {first[1][0]}x{first[1][1]} like {first[0]}"
        )
    return first


def load_blender_split(
    scene_dir: str | os.PathLike[str],
    split: str,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    downscale: int = 1,
    max_images: int | None = None,
    alpha: str = "auto",
) -> BlenderSplit:
    """Load ``<scene_dir>/transforms_<split>.json`` and its images (the first ``max_images`` frames).

    Images are downscaled by the integer ``downscale`` (see ``downscale_rgba``; the focal length scales
    with them) and composited on ``background``. ``alpha`` says whether frames must have an alpha channel
    (``ALPHA_POLICIES``). Every malformed input raises a one-line ``DataError``.
    """
    scene_dir = Path(scene_dir)
    background, downscale = _check_options(background, downscale, max_images)
    if alpha not in ALPHA_POLICIES:
        raise ConfigError(f"dataset.alpha={alpha!r}: expected one of {list(ALPHA_POLICIES)}")
    transforms = scene_dir / f"transforms_{split}.json"
    meta = _read_transforms(transforms)
    frames = meta["frames"][:max_images]

    images, alphas, c2w, names, files = [], [], [], [], []
    first: tuple[Path, tuple[int, int]] | None = None
    first_alpha: tuple[Path, bool] | None = None
    for index, frame in enumerate(frames):
        matrix, path, rgba, has_alpha = _read_frame(scene_dir, transforms, index, frame)
        first = _check_size(path, rgba, first, downscale)
        first_alpha = _check_alpha(path, has_alpha, alpha, first_alpha)
        rgba = downscale_rgba(rgba, downscale)
        opacity = rgba[..., 3:]
        images.append(rgba[..., :3] * opacity + background * (1.0 - opacity))
        alphas.append(opacity[..., 0])
        c2w.append(matrix)
        names.append(path.stem)
        files.append(path)

    height, width = images[0].shape[:2]
    angle = float(meta["camera_angle_x"])
    return BlenderSplit(
        images=np.stack(images).astype(np.float32),
        alphas=np.stack(alphas).astype(np.float32),
        c2w=np.stack(c2w).astype(np.float32),
        focal=focal_from_fov(angle, width),
        width=width,
        height=height,
        names=names,
        camera_angle_x=angle,
        files=files,
    )


def scene_dir(cfg) -> Path:
    """The folder of the scene this job fits: `<paths.scenes>/<task.scene>`."""
    return Path(cfg.paths.scenes) / str(cfg.task.scene)


def load_split(cfg, split: str, max_images: int | None = None):
    """A Blender-format split of this job's scene, composited on `dataset.background`."""
    return load_blender_split(
        scene_dir(cfg),
        split,
        background=tuple(cfg.dataset.background),
        downscale=int(cfg.dataset.get("downscale", 1) or 1),
        max_images=max_images,
        alpha=str(cfg.dataset.alpha),
    )
