"""Empty-space skipping with an occupancy grid: which samples of a ray the field is evaluated at.

An `OccupancyGrid` covers an axis-aligned box with `resolution` cells per axis and keeps, per cell, an
exponential moving maximum of the field's density (`ema`) and an occupancy bit (`occupied`). A model
that has one evaluates its MLP only on the samples whose cell is occupied (`gather_samples` /
`scatter_samples`): the others get density 0 and zero colour (and zero normals), which the compositing
weights then ignore. The models' equations are unchanged: where the field's density is exactly zero in
every unoccupied cell, rendering with the grid equals rendering without it.

The update rule is Instant-NGP's (Müller et al. 2022, "Instant Neural Graphics Primitives with a
Multiresolution Hash Encoding", Sec. 4 and Appendix E.2: every 16 steps, the density at one random point
of each cell, ema <- max(0.95 ema, density), a cell occupied when ema exceeds a threshold, 0.01 there)
as NerfAcc implements it (Li et al. 2023, "NerfAcc: Efficient Sampling Accelerates NeRFs",
`OccGridEstimator.update_every_n_steps`): every cell evaluated during a warm-up, then a random quarter of
the cells plus as many occupied ones, and the threshold min(threshold, mean(ema)) so that a scene of low
density everywhere is not emptied. Here the grid stays all occupied until `warmup_steps` (the density
of a barely trained field says little), then follows the rule.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence

import torch
from torch import Tensor, nn

#: The point densities the grid is updated with: points (P, 3) -> density (P,).
DensityFn = Callable[[Tensor], Tensor]


def cell_indices(points: Tensor, aabb: Tensor, resolution: int) -> tuple[Tensor, Tensor]:
    """(flat cell index (...), inside (...)) of points (..., 3) in the box aabb = [min xyz, max xyz]
    divided into resolution^3 cells: cell (i, j, k) holds min + [i, i + 1) * (max - min) / resolution
    per axis, the upper bound belonging to the last cell. Points outside the box get index 0 and
    inside False."""
    lo, hi = aabb[:3], aabb[3:]
    inside = ((points >= lo) & (points <= hi)).all(dim=-1)
    ijk = torch.floor((points - lo) / (hi - lo) * resolution).long().clamp_(0, resolution - 1)
    flat = (ijk[..., 0] * resolution + ijk[..., 1]) * resolution + ijk[..., 2]
    return torch.where(inside, flat, torch.zeros_like(flat)), inside


def cell_points(cells: Tensor, aabb: Tensor, resolution: int, jitter: Tensor) -> Tensor:
    """Points (P, 3) in the given flat cells (P,): min + (ijk + jitter) * cell size, jitter (P, 3) in
    [0, 1) (0.5: the cell centres)."""
    ijk = torch.stack(
        [cells // resolution**2, (cells // resolution) % resolution, cells % resolution], dim=-1
    )
    lo, hi = aabb[:3], aabb[3:]
    return lo + (ijk.to(jitter.dtype) + jitter) * (hi - lo) / resolution


def ema_update(ema: Tensor, cells: Tensor, density: Tensor, decay: float) -> Tensor:
    """ema with ema[c] <- max(decay * ema[c], density) at the (distinct) flat cells c (Instant-NGP,
    Appendix E.2); the other cells unchanged (a new tensor)."""
    out = ema.clone()
    out[cells] = torch.maximum(ema[cells] * decay, density.to(ema.dtype))
    return out


def occupancy_from_ema(ema: Tensor, threshold: float) -> Tensor:
    """Occupied cells: ema > min(threshold, mean(ema)) (NerfAcc's rule, Li et al. 2023)."""
    return ema > torch.clamp(ema.mean(), max=threshold)


def gather_samples(mask: Tensor, per_sample: Mapping[str, Tensor], per_ray: Mapping[str, Tensor]):
    """The samples where mask (N, S) is True as one dense batch of M rays of one sample each: per-sample
    tensors (N, S, ...) -> (M, 1, ...), per-ray tensors (N, ...) -> (M, ...) (each sample's own ray)."""
    ray_of_sample = mask.nonzero()[:, 0]
    samples = {k: v[mask][:, None] for k, v in per_sample.items()}
    rays = {k: v[ray_of_sample] for k, v in per_ray.items()}
    return samples, rays


def scatter_samples(mask: Tensor, values: Mapping[str, Tensor]) -> dict[str, Tensor]:
    """The inverse of `gather_samples` on a field's outputs: each (M, 1, ...) -> (N, S, ...), zero where
    mask is False (differentiable w.r.t. the values)."""
    full: dict[str, Tensor] = {}
    for key, value in values.items():
        out = value.new_zeros((*mask.shape, *value.shape[2:]))
        out[mask] = value[:, 0]
        full[key] = out
    return full


class OccupancyGrid(nn.Module):
    """The occupancy grid of one radiance field (state: buffers, so checkpoints keep it).

    Args:
        aabb: the box, [x_min, y_min, z_min, x_max, y_max, z_max] in world units.
        resolution: cells per axis.
        update_every: steps between updates (Instant-NGP and NerfAcc: 16).
        decay: the moving maximum's decay per update (0.95).
        threshold: density (per unit length along the ray) above which a cell is occupied, capped by the
            mean (`occupancy_from_ema`).
        warmup_steps: the grid is all occupied, and every update evaluates every cell, before this step
            (NerfAcc evaluates every cell for its first 256 steps); the first update from this step on
            evaluates every cell too.
        sample_fraction: after the warm-up an update evaluates this share of the cells, drawn uniformly,
            plus as many occupied cells (NerfAcc: 1/4).
        occupied_outside: whether points outside the box count as occupied (evaluated).
        chunk: points per density evaluation of an update (memory).
    """

    def __init__(
        self,
        *,
        aabb: Sequence[float],
        resolution: int,
        update_every: int,
        decay: float,
        threshold: float,
        warmup_steps: int,
        sample_fraction: float,
        occupied_outside: bool,
        chunk: int,
    ) -> None:
        super().__init__()
        self.resolution, self.update_every, self.decay = resolution, update_every, decay
        self.threshold, self.warmup_steps, self.sample_fraction = threshold, warmup_steps, sample_fraction
        self.occupied_outside, self.chunk = occupied_outside, chunk
        cells = resolution**3
        self.register_buffer("aabb", torch.tensor(list(aabb), dtype=torch.float32), persistent=False)
        self.register_buffer("ema", torch.zeros(cells))
        self.register_buffer("occupied", torch.ones(cells, dtype=torch.bool))

    def occupied_at(self, points: Tensor) -> Tensor:
        """Whether each point (..., 3) lies in an occupied cell (outside the box: `occupied_outside`)."""
        cells, inside = cell_indices(points, self.aabb.to(points.dtype), self.resolution)
        return torch.where(inside, self.occupied[cells], self.occupied_outside)

    def cells_to_update(self, step: int, generator: torch.Generator) -> Tensor:
        """Every cell during the warm-up and at the first update after it (so that the first occupancy
        bits come from every cell, whatever `warmup_steps` is); then a `sample_fraction` of the cells
        uniformly at random and as many occupied ones (NerfAcc's choice), without repeats (sorted flat
        indices, on the CPU)."""
        cells = self.occupied.numel()
        if step < self.warmup_steps + self.update_every:
            return torch.arange(cells)
        k = max(1, int(cells * self.sample_fraction))
        uniform = torch.randperm(cells, generator=generator)[:k]
        occupied = self.occupied.cpu().nonzero()[:, 0]
        occupied = occupied[torch.randperm(len(occupied), generator=generator)[:k]]
        return torch.unique(torch.cat([uniform, occupied]))

    @torch.no_grad()
    def update(self, density_fn: DensityFn, step: int, generator: torch.Generator) -> bool:
        """At every `update_every`-th step: the density at one uniformly jittered point (drawn from the
        CPU `generator`) of each cell of `cells_to_update`, folded into the moving maximum, then the
        occupancy bits (left all occupied during the warm-up). Returns whether it updated."""
        if step % self.update_every != 0:
            return False
        cells = self.cells_to_update(step, generator)
        jitter = torch.rand((len(cells), 3), generator=generator)
        points = cell_points(cells, self.aabb.cpu(), self.resolution, jitter).to(self.ema.device)
        density = torch.cat([density_fn(part) for part in points.split(self.chunk)])
        self.ema.copy_(ema_update(self.ema, cells.to(self.ema.device), density, self.decay))
        if step >= self.warmup_steps:
            self.occupied.copy_(occupancy_from_ema(self.ema, self.threshold))
        return True

    def extra_repr(self) -> str:
        share = float(self.occupied.float().mean())
        box = [round(c, 6) for c in self.aabb.tolist()]
        return f"resolution={self.resolution}, aabb={box}, occupied={share:.3f}"
