"""Random training rays of a Blender-format scene with their target colours, reproducible per step."""

from __future__ import annotations

import numpy as np
import torch

from src.data.blender import BlenderSplit
from src.data.rays import as_c2w, rays_for_pixels
from src.errors import ConfigError


def step_seed(seed: int, step: int, stream: int = 0) -> int:
    """A 63-bit generator seed unique to (seed, step), the same in every process and on every platform;
    `stream` > 0 gives another independent seed per (seed, step) (e.g. the occupancy grid's jitter)."""
    entropy = [int(seed), int(step)] + ([int(stream)] if stream else [])
    return int(np.random.SeedSequence(entropy).generate_state(1, np.uint64)[0] >> 1)


#: How a batch's pixels are spread over the training images (`task.train.batching`).
BATCHING = ("all_images", "single_image")


class RayBatcher:
    """Random training rays with their target colours, reproducible per step.

    ``batch(step)`` draws ``batch_size`` pixels uniformly (with replacement) over all images with a
    ``torch.Generator`` seeded by ``step_seed(seed, step)``: the same (seed, step) gives the same batch,
    so a run resumed at step k sees exactly the batches it would have seen. Rays are made per batch from
    the drawn (cam, row, col) indices (``rays_for_pixels``), so memory is the images plus one batch,
    never all N x H x W rays.

    ``batching``: ``all_images`` (the default, NeRF's and multinerf's) draws each pixel's image
    independently; ``single_image`` (mip-NeRF's Blender config, ``batching = 'single_image'``; NeRF's
    released code's ``no_batching``) first draws one image for the step, then all the batch's pixels from
    it. Either way the batch depends only on (seed, step).

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
        batching: str = "all_images",
        device: str | torch.device | None = None,
    ):
        images = torch.as_tensor(images)  # shares memory with a float32 numpy array
        if images.ndim != 4 or images.shape[-1] != 3:
            raise ValueError(f"images: expected (N, H, W, 3), got shape {tuple(images.shape)}")
        if batch_size < 1:
            raise ConfigError(f"batch_size: expected >= 1, got {batch_size}")
        if batching not in BATCHING:
            raise ConfigError(f"batching={batching!r}: expected one of {list(BATCHING)}")
        if not 0.0 < precrop_frac <= 1.0:
            raise ConfigError(f"precrop_frac: expected a fraction in (0, 1], got {precrop_frac}")
        self.device = torch.device(device) if device is not None else images.device
        self.images = images.to(self.device, torch.float32)
        self.c2w = as_c2w(c2w, self.device)
        if self.c2w.shape[0] != self.images.shape[0]:
            raise ValueError(f"c2w has {self.c2w.shape[0]} cameras for {self.images.shape[0]} images")
        self.n_images, self.height, self.width = (int(s) for s in self.images.shape[:3])
        self.focal, self.near, self.far = float(focal), float(near), float(far)
        self.batch_size, self.seed = int(batch_size), int(seed)
        self.precrop_iters, self.precrop_frac = int(precrop_iters), float(precrop_frac)
        self.batching = batching

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
        if self.batching == "single_image":
            cam = torch.randint(0, self.n_images, (1,), generator=gen).expand(n).clone()
        else:
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
