"""Blender synthetic (nerf_synthetic) scenes: loading, camera rays and random ray batches for training.

Format (Mildenhall et al. 2020): ``<scene>/transforms_{train,val,test}.json`` with

    {"camera_angle_x": <horizontal field of view, radians>,
     "frames": [{"file_path": "./train/r_0", "transform_matrix": <4x4 camera-to-world>}, ...]}

and RGBA PNGs with *straight* (non-premultiplied) alpha. ``file_path`` is relative to the scene folder
and usually has no extension (".png" is appended when the path as written is not a file). Cameras follow
the OpenGL convention: the camera looks down its -z axis, +y is up and +x is right in the image. The
pinhole's principal point is the image centre and ``focal = 0.5 W / tan(0.5 camera_angle_x)`` pixels.

Pixel (row j, column i) covers [i, i + 1) x [j, j + 1) in image coordinates; rays go through its centre
(i + 0.5, j + 0.5) (several public NeRF codes shoot through the corner i, j instead: a half-pixel shift).
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from src.errors import ConfigError, DataError

#: mip-NeRF's radius of the cone through a pixel: the pixel footprint scaled by 2 / sqrt(12), so the
#: cone's cross-section has the variance of a uniform distribution over the (square) pixel.
RADIUS_SCALE = 2.0 / math.sqrt(12.0)
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


def focal_from_fov(camera_angle_x: float, width: int) -> float:
    """Focal length in pixels of a pinhole with horizontal field of view ``camera_angle_x`` (radians)."""
    return 0.5 * width / math.tan(0.5 * camera_angle_x)


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


def _read_rgba(path: Path) -> np.ndarray:
    """(H, W, 4) float32 in [0, 1] (straight alpha; alpha 1 when the file has none)."""
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode == "P":  # palette: lossless expansion, keeping a transparency entry if any
                img = img.convert("RGBA" if "transparency" in img.info else "RGB")
            if img.mode not in ("RGB", "RGBA"):
                raise DataError(
                    f"{path}: image has {len(img.getbands())} channel(s) (PIL mode {img.mode}); expected 3 "
                    "(RGB) or 4 (RGBA)"
                )
            pixels = np.asarray(img)
    except (OSError, Image.DecompressionBombError) as err:
        raise DataError(f"{path}: unreadable image ({err}); expected an RGB(A) PNG") from err
    if pixels.dtype != np.uint8:
        raise DataError(f"{path}: image samples are {pixels.dtype}; expected 8-bit")
    rgba = pixels.astype(np.float32) / 255.0
    if rgba.shape[-1] == 3:
        rgba = np.concatenate([rgba, np.ones_like(rgba[..., :1])], axis=-1)
    return rgba


def downscale_rgba(rgba: np.ndarray, factor: int) -> np.ndarray:
    """Area-average (H, W, 4) straight-alpha RGBA by an integer ``factor`` (H, W divisible by it).

    Averages *premultiplied* colour (rgb * alpha) and alpha over each factor x factor block, then
    returns straight colour (0 where the block is fully transparent). Averaging straight colour instead
    lets the arbitrary colour stored in transparent pixels (often black) bleed into object edges as a
    dark halo. A numpy reshape-mean in float32 is used rather than PIL's resize: it is exactly the box
    average over the block (the pixel footprint that mip-NeRF's multiscale data assumes), with no
    requantisation to 8 bits in between and no dependence on the PIL version's alpha handling.
    """
    if factor == 1:
        return rgba
    h, w, c = rgba.shape
    premul = np.concatenate([rgba[..., :3] * rgba[..., 3:], rgba[..., 3:]], axis=-1)
    blocks = premul.reshape(h // factor, factor, w // factor, factor, c).mean(axis=(1, 3))
    alpha = blocks[..., 3:]
    rgb = np.divide(blocks[..., :3], alpha, out=np.zeros_like(blocks[..., :3]), where=alpha > 0)
    return np.concatenate([rgb, alpha], axis=-1).astype(np.float32)


def load_blender_split(
    scene_dir: str | os.PathLike[str],
    split: str,
    background: Sequence[float] = (1.0, 1.0, 1.0),
    downscale: int = 1,
    max_images: int | None = None,
) -> BlenderSplit:
    """Load ``<scene_dir>/transforms_<split>.json`` and its images (the first ``max_images`` frames).

    Images are downscaled by the integer ``downscale`` (see ``downscale_rgba``; the focal length scales
    with them) and composited on ``background``. Every malformed input raises a one-line ``DataError``.
    """
    scene_dir = Path(scene_dir)
    background = np.asarray(background, dtype=np.float32)
    if background.shape != (3,):
        raise ConfigError(f"background: expected 3 values (RGB), got {background.tolist()}")
    if isinstance(downscale, bool) or int(downscale) != downscale or downscale < 1:
        raise ConfigError(f"downscale: expected an integer >= 1, got {downscale!r}")
    downscale = int(downscale)
    if max_images is not None and max_images < 1:
        raise ConfigError(f"max_images: expected an integer >= 1 or null, got {max_images!r}")
    transforms = scene_dir / f"transforms_{split}.json"
    meta = _read_transforms(transforms)
    frames = meta["frames"][:max_images]

    images, alphas, c2w, names, files = [], [], [], [], []
    first: tuple[Path, tuple[int, int]] | None = None
    for index, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise DataError(f"{transforms}: frames[{index}] is a {type(frame).__name__}; expected an object")
        for key in ("file_path", "transform_matrix"):
            if key not in frame:
                raise DataError(
                    f"{transforms}: frames[{index}] is missing key '{key}'; found {sorted(frame)}"
                )
        matrix = _check_matrix(transforms, index, frame["transform_matrix"])
        path = _image_file(scene_dir, transforms, index, frame["file_path"])
        rgba = _read_rgba(path)
        size = (rgba.shape[1], rgba.shape[0])
        if first is None:
            first = (path, size)
            if size[0] % downscale or size[1] % downscale:
                raise DataError(
                    f"{path}: image is {size[0]}x{size[1]}, not divisible by downscale={downscale}; "
                    "expected width and height that are multiples of it"
                )
        elif size != first[1]:
            raise DataError(
                f"{path}: image is {size[0]}x{size[1]}; expected {first[1][0]}x{first[1][1]} like {first[0]}"
            )
        rgba = downscale_rgba(rgba, downscale)
        alpha = rgba[..., 3:]
        images.append(rgba[..., :3] * alpha + background * (1.0 - alpha))
        alphas.append(alpha[..., 0])
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


# ----------------------------------------------------------------------------------------------- rays


def _as_c2w(c2w, device=None) -> torch.Tensor:
    """(N, 4, 4) or (N, 3, 4) float32 tensor from a tensor / array; a single (4, 4) becomes N = 1."""
    t = torch.as_tensor(np.asarray(c2w) if not isinstance(c2w, torch.Tensor) else c2w, device=device)
    t = t.to(torch.float32)
    if t.ndim == 2:
        t = t[None]
    if t.ndim != 3 or t.shape[-2] not in (3, 4) or t.shape[-1] != 4:
        raise ValueError(f"c2w: expected (N, 4, 4) or (N, 3, 4), got shape {tuple(t.shape)}")
    return t


def camera_directions(
    row: torch.Tensor, col: torch.Tensor, focal: float, width: int, height: int
) -> torch.Tensor:
    """Camera-space directions (..., 3) through the centres of pixels (row, col), OpenGL convention:

        d = ((col + 0.5 - W / 2) / f, -(row + 0.5 - H / 2) / f, -1)

    (z = -1, not normalised, so t along the ray is the distance along the camera axis).
    """
    x = (col.to(torch.float32) + 0.5 - 0.5 * width) / focal
    y = -(row.to(torch.float32) + 0.5 - 0.5 * height) / focal
    return torch.stack([x, y, -torch.ones_like(x)], dim=-1)


def pixel_footprint_radii(directions: torch.Tensor) -> torch.Tensor:
    """mip-NeRF cone radii (..., H, W, 1) from a grid of ray directions (..., H, W, 3):

        radii = ||d[i + 1] - d[i]|| * 2 / sqrt(12)

    the distance between horizontally neighbouring (unnormalised) directions, the last column
    repeating its left neighbour (mip-NeRF ``generate_rays``; its code differences the first grid
    axis, which is the same for square pixels). For a pinhole this is ||R e_x|| / f everywhere.
    """
    if directions.shape[-2] < 2:
        raise ValueError(f"pixel_footprint_radii: need at least 2 columns, got {tuple(directions.shape)}")
    dx = torch.linalg.norm(directions[..., 1:, :] - directions[..., :-1, :], dim=-1)
    dx = torch.cat([dx, dx[..., -1:]], dim=-1)
    return dx[..., None] * RADIUS_SCALE


def _ray_dict(origins, directions, radii, near: float, far: float) -> dict[str, torch.Tensor]:
    ones = torch.ones_like(radii)
    return {
        "origins": origins,
        "directions": directions,
        "viewdirs": directions / torch.linalg.norm(directions, dim=-1, keepdim=True),
        "radii": radii,
        "near": ones * near,
        "far": ones * far,
    }


def generate_rays(
    c2w, focal: float, width: int, height: int, near: float, far: float
) -> dict[str, torch.Tensor]:
    """Rays through every pixel centre of every camera, flattened to (n_cams * H * W, C).

    Order: camera, then row (top to bottom), then column (left to right): ray index
    ``(n * H + row) * W + col``. Keys: ``origins`` (camera centre), ``directions`` (R @ d_cam from
    ``camera_directions``, not normalised), ``viewdirs`` (unit), ``radii`` (mip-NeRF, see
    ``pixel_footprint_radii``), ``near`` and ``far`` (all (M, 3) or (M, 1), float32, on c2w's device).
    ``c2w`` is (N, 4, 4), (N, 3, 4) or a single (4, 4) OpenGL camera-to-world matrix.
    """
    c2w = _as_c2w(c2w)
    device = c2w.device
    rows = torch.arange(height, device=device)
    cols = torch.arange(width, device=device)
    grid_r, grid_c = torch.meshgrid(rows, cols, indexing="ij")
    d_cam = camera_directions(grid_r, grid_c, focal, width, height)  # (H, W, 3)
    rot = c2w[:, :3, :3]
    directions = torch.einsum("nij,hwj->nhwi", rot, d_cam).reshape(-1, 3)
    origins = c2w[:, None, :3, 3].expand(-1, height * width, -1).reshape(-1, 3)
    radius = torch.linalg.norm(rot[:, :, 0], dim=-1) / focal * RADIUS_SCALE  # (N,)
    radii = radius[:, None].expand(-1, height * width).reshape(-1, 1)
    return _ray_dict(origins, directions, radii, near, far)


def rays_for_pixels(
    c2w: torch.Tensor,
    cam: torch.Tensor,
    row: torch.Tensor,
    col: torch.Tensor,
    focal: float,
    width: int,
    height: int,
    near: float,
    far: float,
) -> dict[str, torch.Tensor]:
    """The rays of ``generate_rays`` for the pixels (cam[k], row[k], col[k]) only, shape (M, C)."""
    c2w = _as_c2w(c2w)
    rot = c2w[cam, :3, :3]  # (M, 3, 3)
    d_cam = camera_directions(row, col, focal, width, height)
    directions = (rot @ d_cam[..., None])[..., 0]
    radii = torch.linalg.norm(rot[:, :, 0], dim=-1, keepdim=True) / focal * RADIUS_SCALE
    return _ray_dict(c2w[cam, :3, 3], directions, radii, near, far)


# -------------------------------------------------------------------------------------------- batches


def step_seed(seed: int, step: int) -> int:
    """A 63-bit generator seed unique to (seed, step), the same in every process and on every platform."""
    return int(np.random.SeedSequence([int(seed), int(step)]).generate_state(1, np.uint64)[0] >> 1)


class RayBatcher:
    """Random training rays with their target colours, reproducible per step.

    ``batch(step)`` draws ``batch_size`` pixels uniformly (with replacement) over all images with a
    ``torch.Generator`` seeded by ``step_seed(seed, step)``: the same (seed, step) gives the same batch,
    so a run resumed at step k sees exactly the batches it would have seen. Rays are made per batch from
    the drawn (cam, row, col) indices (``rays_for_pixels``), so memory is the images plus one batch,
    never all N x H x W rays.

    Centre-crop warm-up (NeRF's ``precrop_iters`` / ``precrop_frac``): for steps < ``precrop_iters``
    only the central rows [H/2 - dH, H/2 + dH) and columns [W/2 - dW, W/2 + dW) are drawn, with
    dH = int(H // 2 * precrop_frac) (dW likewise), so mostly-white scenes do not collapse to background
    early.
    """

    def __init__(
        self,
        images,
        c2w,
        focal: float,
        *,
        near: float,
        far: float,
        batch_size: int,
        seed: int,
        precrop_iters: int = 0,
        precrop_frac: float = 0.5,
        device: str | torch.device | None = None,
    ):
        images = torch.as_tensor(images)  # shares memory with a float32 numpy array
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"images: expected (N, H, W, 3), got shape {tuple(images.shape)}")
        if batch_size < 1:
            raise ConfigError(f"batch_size: expected >= 1, got {batch_size}")
        if not 0.0 < precrop_frac <= 1.0:
            raise ConfigError(f"precrop_frac: expected a fraction in (0, 1], got {precrop_frac}")
        self.device = torch.device(device) if device is not None else images.device
        self.images = images.to(self.device, torch.float32)
        self.c2w = _as_c2w(c2w, self.device)
        if self.c2w.shape[0] != self.images.shape[0]:
            raise ValueError(f"c2w has {self.c2w.shape[0]} cameras for {self.images.shape[0]} images")
        self.n_images, self.height, self.width = (int(s) for s in self.images.shape[:3])
        self.focal, self.near, self.far = float(focal), float(near), float(far)
        self.batch_size, self.seed = int(batch_size), int(seed)
        self.precrop_iters, self.precrop_frac = int(precrop_iters), float(precrop_frac)

    @classmethod
    def from_split(cls, split: BlenderSplit, **kwargs) -> RayBatcher:
        """A batcher over a loaded split (``near``, ``far``, ``batch_size``, ``seed`` ... as keywords)."""
        return cls(split.images, split.c2w, split.focal, **kwargs)

    def pixel_ranges(self, step: int) -> tuple[tuple[int, int], tuple[int, int]]:
        """([row_lo, row_hi), [col_lo, col_hi)) the pixels of ``step`` are drawn from."""
        if step < self.precrop_iters:
            dh = max(int(self.height // 2 * self.precrop_frac), 1)
            dw = max(int(self.width // 2 * self.precrop_frac), 1)
            h2, w2 = self.height // 2, self.width // 2
            return (max(h2 - dh, 0), min(h2 + dh, self.height)), (max(w2 - dw, 0), min(w2 + dw, self.width))
        return (0, self.height), (0, self.width)

    def indices(self, step: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(cam, row, col) int64 tensors of the ``batch_size`` pixels of ``step`` (on CPU)."""
        if step < 0:
            raise ValueError(f"step must be >= 0, got {step}")
        gen = torch.Generator(device="cpu").manual_seed(step_seed(self.seed, step))
        (r0, r1), (c0, c1) = self.pixel_ranges(step)
        n = self.batch_size
        cam = torch.randint(0, self.n_images, (n,), generator=gen)
        row = torch.randint(r0, r1, (n,), generator=gen)
        col = torch.randint(c0, c1, (n,), generator=gen)
        return cam, row, col

    def batch(self, step: int) -> dict[str, torch.Tensor]:
        """Rays (see ``generate_rays`` keys) + ``rgb`` (B, 3) targets + the ``cam``/``row``/``col`` drawn."""
        cam, row, col = (t.to(self.device) for t in self.indices(step))
        rays = rays_for_pixels(
            self.c2w, cam, row, col, self.focal, self.width, self.height, self.near, self.far
        )
        rays["rgb"] = self.images[cam, row, col]
        rays.update(cam=cam, row=row, col=col)
        return rays
