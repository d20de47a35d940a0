"""Pinhole camera rays of Blender-format scenes: through every pixel centre, or through chosen pixels.

Cameras follow the OpenGL convention: the camera looks down its -z axis, +y is up and +x is right in the
image. The pinhole's principal point is the image centre and ``focal = 0.5 W / tan(0.5 camera_angle_x)``
pixels.

Pixel (row j, column i) covers [i, i + 1) x [j, j + 1) in image coordinates; rays go through its centre
(i + 0.5, j + 0.5) (several public NeRF codes shoot through the corner i, j instead: a half-pixel shift).
"""

from __future__ import annotations

import math

import numpy as np
import torch

#: mip-NeRF's radius of the cone through a pixel: the pixel footprint scaled by 2 / sqrt(12), so the
#: cone's cross-section has the variance of a uniform distribution over the (square) pixel.
RADIUS_SCALE = 2.0 / math.sqrt(12.0)


def focal_from_fov(camera_angle_x: float, width: int) -> float:
    """Focal length in pixels of a pinhole with horizontal field of view ``camera_angle_x`` (radians)."""
    return 0.5 * width / math.tan(0.5 * camera_angle_x)


def as_c2w(c2w, device=None) -> torch.Tensor:
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
    c2w = as_c2w(c2w)
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
    c2w = as_c2w(c2w)
    rot = c2w[cam, :3, :3]  # (M, 3, 3)
    d_cam = camera_directions(row, col, focal, width, height)
    directions = (rot @ d_cam[..., None])[..., 0]
    radii = torch.linalg.norm(rot[:, :, 0], dim=-1, keepdim=True) / focal * RADIUS_SCALE
    return _ray_dict(c2w[cam, :3, 3], directions, radii, near, far)
