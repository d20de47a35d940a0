"""The temporal loss of the volumetric denoiser (Zhu et al. 2023, the Pixar/Disney SIGGRAPH talk
"Denoising Production Volumetric Rendering": "a temporal loss on pixel derivatives to penalise
inconsistencies between successive frames", added to the SMAPE reconstruction loss by a weighted sum).

On a training sample of k consecutive frames (N, k, C, H, W), with Δt x = x_{t+1} - x_t:

- `signed` (default): mean | Δt output - Δt reference |: the output must change between frames as the
  reference does; zero for a static sequence whose output equals the reference, positive for flicker.
- `abs`: mean | |Δt output| - |Δt reference| |: the magnitudes only, the |difference| variant of
  Chaitanya et al. 2017 ("Interactive reconstruction of Monte Carlo image sequences", Sec. 5.2).

`warp`: frame t+1 is first resampled along the motion vectors (`warp_to_previous`), so that the
difference is taken along each surface point's path instead of at a fixed pixel: camera motion then
no longer counts as change. Motion vectors describe surfaces, not media (a volume has no single
depth), so this is an option; the default compares at fixed pixels, where the reference's own
differences already carry the motion.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from src.errors import ConfigError

TEMPORAL_MODES = ("signed", "abs")


def warp_to_previous(next_frames: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
    """Frame t+1 seen from frame t: out[..., y, x] = next[..., y + m_y, x + m_x] with m = motion of frame
    t (pixels to the next frame), bilinear, border-clamped. (M, C, H, W) and (M, 2, H, W) -> (M, C, H, W)."""
    m, _, h, w = next_frames.shape
    ys, xs = torch.meshgrid(
        torch.arange(h, dtype=motion.dtype, device=motion.device),
        torch.arange(w, dtype=motion.dtype, device=motion.device),
        indexing="ij",
    )
    x = xs + motion[:, 0]
    y = ys + motion[:, 1]
    # grid_sample's normalised coordinates with align_corners=True: -1 and 1 are the outer pixel centres.
    grid = torch.stack((2 * x / max(w - 1, 1) - 1, 2 * y / max(h - 1, 1) - 1), dim=-1)
    return F.grid_sample(next_frames, grid, mode="bilinear", padding_mode="border", align_corners=True)


def frame_differences(frames: torch.Tensor, motion: torch.Tensor | None = None) -> torch.Tensor:
    """Δt of (N, k, C, H, W) frames: (N, k-1, C, H, W), frame t+1 warped to t when `motion` (N, k, 2, H, W)
    is given."""
    following = frames[:, 1:]
    if motion is not None:
        n, k1 = following.shape[:2]
        flat = warp_to_previous(following.flatten(0, 1), motion[:, :-1].flatten(0, 1).to(frames.dtype))
        following = flat.view(n, k1, *flat.shape[1:])
    return following - frames[:, :-1]


def temporal_loss(
    output: torch.Tensor,
    reference: torch.Tensor,
    mode: str = "signed",
    motion: torch.Tensor | None = None,
) -> torch.Tensor:
    """The temporal loss of (N, k, C, H, W) output and reference frames, k >= 2 (module docstring)."""
    if mode not in TEMPORAL_MODES:
        raise ConfigError(f"dataset.train.temporal_mode={mode!r}: expected one of {list(TEMPORAL_MODES)}")
    if output.ndim != 5 or output.shape != reference.shape or output.shape[1] < 2:
        raise ValueError(
            f"temporal_loss: expected (N, k >= 2, C, H, W) output and reference of one shape, got "
            f"{tuple(output.shape)} and {tuple(reference.shape)}"
        )
    d_out, d_ref = frame_differences(output, motion), frame_differences(reference, motion)
    if mode == "abs":
        d_out, d_ref = d_out.abs(), d_ref.abs()
    return (d_out - d_ref).abs().mean()
