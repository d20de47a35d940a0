"""NeRF, mip-NeRF and Ref-NeRF behind one interface (built from config by `builders.py`; chunked rendering
in `inference.py`, parameter and FLOP summary in `summary.py`).

Every model renders two levels (coarse, fine) of the same rays:

    coarse: stratified intervals on [near, far] -> field -> weights (NeRF Eq. 3)
    fine:   intervals resampled from the coarse weights (gradients stopped) -> field -> weights

- `NeRF` (Mildenhall et al. 2020): PE of the interval midpoints, separate coarse and fine MLPs, the
  fine level on the coarse samples merged with importance samples (64 + 128), loss MSE_c + MSE_f.
- `MipNeRF` (Barron et al. 2021): IPE of each interval's conical frustum, one MLP for both levels,
  blurred resampling (padding 0.01), loss 0.1 MSE_c + MSE_f.
- `RefNeRF` (Verbin et al. 2022): mip-NeRF's sampling and IPE with `RefNerfMLP`, plus the orientation
  and predicted-normal regularisers (Ref-NeRF Eq. 11-12).

The encodings are objects (`encodings.Encoding`) given by the builders: a model reads the position
encoding's `reads` to compute each interval's inputs (`interval_inputs`: the midpoint for a point
encoding, the conical frustum's Gaussian for an integrated one) and never branches on the encoding's
class, so NeRF and mip-NeRF are one code path (`MipNeRF` differs by its name and its config).

With an `OccupancyGrid` (`occupancy.py`; None by default) the three models run their MLP only on the
samples whose position (NeRF: the interval midpoint; mip-NeRF, Ref-NeRF: the frustum Gaussian's mean)
lies in an occupied cell; the other samples get density 0 and zero colour (normals), and everything
after the field (weights, resampling, losses) is the same code on the same shapes.

Rays are a dict of (N, k) tensors: origins, directions (camera-space z = -1 directions rotated to world,
not normalised: t is then the camera depth), viewdirs (unit), radii (cone radius at t = 1), near, far.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Protocol

import torch
from torch import Tensor, nn

from src.models.nerf.directional import l2_normalize
from src.models.nerf.encodings import Encoding, cast_rays
from src.models.nerf.fields import NerfMLP, RefNerfMLP
from src.models.nerf.occupancy import OccupancyGrid, gather_samples, scatter_samples
from src.models.nerf.sampling import resample_draws, resample_tdist, stratified_samples
from src.models.nerf.volume import compute_alpha_weights, volumetric_rendering

RAY_KEYS = ("origins", "directions", "viewdirs", "radii", "near", "far")
LEVELS = ("coarse", "fine")
ORIENTATION_NORMALS = ("pred", "density")

Rays = Mapping[str, Tensor]


class SampleField(Protocol):
    """A field on per-sample inputs (N, S, ...) and per-ray inputs (N, ...) -> per-sample outputs."""

    def __call__(self, samples: dict[str, Tensor], rays: dict[str, Tensor]) -> dict[str, Tensor]: ...


def interval_inputs(reads: str, rays: Rays, tdist: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
    """(positions (N, S, 3), the per-sample inputs of an encoding that reads `reads`) of the intervals
    [tdist[i], tdist[i+1]] of every ray: for "point" the midpoints o + t_mid d ({"x"}); for "gaussian"
    each interval's conical frustum as a Gaussian (mip-NeRF Eq. 7-8; {"means", "covs"}, diagonal), whose
    means are the positions."""
    if reads == "gaussian":
        means, covs = cast_rays(tdist, rays["origins"], rays["directions"], rays["radii"], diag=True)
        return means, {"means": means, "covs": covs}
    if reads == "point":
        t_mid = 0.5 * (tdist[..., 1:] + tdist[..., :-1])
        x = rays["origins"][..., None, :] + t_mid[..., None] * rays["directions"][..., None, :]
        return x, {"x": x}
    raise ValueError(f"an encoding of sample positions reads 'point' or 'gaussian', not {reads!r}")


def point_inputs(reads: str, points: Tensor) -> dict[str, Tensor]:
    """The inputs of an encoding that reads `reads` for bare points (P, 3) (an occupancy grid's queries):
    the point itself, or a Gaussian of zero covariance (whose IPE is the plain PE)."""
    if reads == "gaussian":
        return {"means": points, "covs": torch.zeros_like(points)}
    if reads == "point":
        return {"x": points}
    raise ValueError(f"an encoding of sample positions reads 'point' or 'gaussian', not {reads!r}")


def at_least_fp32(x: Tensor) -> Tensor:
    """`x` in float32 if in a lower precision (bf16/fp16 under autocast), else unchanged (fp64 stays)."""
    return x.float() if x.dtype in (torch.bfloat16, torch.float16) else x


class NerfModelBase(nn.Module):
    """Two-level volume rendering shared by the three models.

    Subclasses define `evaluate(level, rays, tdist)` (the field on the intervals: a dict with at least
    density (N, S) and rgb (N, S, 3)) and, optionally, `level_extras` / `regularizers`.

    Args:
        coarse_mlp, fine_mlp: the fields of the two levels; fine_mlp None: the coarse one serves both.
        num_coarse_samples: coarse intervals per ray (S_c).
        num_fine_samples: fine samples: importance samples merged with the coarse ones when
            `resample_padding` is None (NeRF, S_f = S_c + n), else the fine intervals (mip-NeRF, S_f = n).
        resample_padding: None (NeRF) or mip-NeRF's histogram padding (`sampling.resample_tdist`).
        lindisp: coarse intervals uniform in 1/t instead of t.
        background: RGB composited behind each ray with weight 1 - acc.
        coarse_loss_mult: weight of the coarse level in the loss (NeRF 1, mip-NeRF 0.1).
        opaque_background: the last interval is 1e10 long (NeRF's released code, Mildenhall et al. 2020:
            any density there makes the ray opaque at the far bound) instead of its real length
            (mip-NeRF, multinerf). See `volume.compute_alpha_weights`.
        occupancy_grid: empty-space skipping (`occupancy.OccupancyGrid`; None: every sample evaluated).
            A subclass uses it through `evaluate_occupied` and gives its density through `point_density`.
    """

    name = "base"
    #: Per-ray outputs of the fine level that `render_rays_chunked` returns.
    render_keys: tuple[str, ...] = ("rgb", "depth", "acc")

    def __init__(
        self,
        coarse_mlp: nn.Module,
        fine_mlp: nn.Module | None,
        *,
        num_coarse_samples: int,
        num_fine_samples: int,
        resample_padding: float | None,
        lindisp: bool = False,
        background: Sequence[float] = (1.0, 1.0, 1.0),
        coarse_loss_mult: float = 1.0,
        opaque_background: bool = False,
        occupancy_grid: OccupancyGrid | None = None,
    ) -> None:
        super().__init__()
        self.opaque_background = opaque_background
        self.occupancy_grid = occupancy_grid  # a submodule (its buffers in the state dict) when given
        self.mlps = nn.ModuleList([coarse_mlp] if fine_mlp is None else [coarse_mlp, fine_mlp])
        self.num_coarse_samples, self.num_fine_samples = num_coarse_samples, num_fine_samples
        self.resample_padding, self.lindisp = resample_padding, lindisp
        self.coarse_loss_mult = coarse_loss_mult
        background_rgb = torch.tensor(list(background), dtype=torch.float32)
        self.register_buffer("background", background_rgb, persistent=False)  # config, not state

    # --- to be defined by the models -------------------------------------------------------------------
    def evaluate(self, level: int, rays: Rays, tdist: Tensor) -> dict[str, Tensor]:
        raise NotImplementedError

    def level_extras(self, fields: dict[str, Tensor], weights: Tensor, rays: Rays) -> dict[str, Tensor]:
        return {}

    def regularizers(self, outputs: list[dict[str, Tensor]]) -> tuple[Tensor | None, dict[str, float]]:
        return None, {}

    def point_density(self, points: Tensor) -> Tensor:
        """The field's density at points (P, 3) -> (P,), from the fine level's MLP (what an occupancy
        grid is updated with)."""
        raise NotImplementedError(f"{type(self).__name__} has no point density (no occupancy grid)")

    # --- shared --------------------------------------------------------------------------------------
    def evaluate_occupied(
        self, points: Tensor, samples: dict[str, Tensor], rays: dict[str, Tensor], field: SampleField
    ) -> dict[str, Tensor]:
        """field(samples, rays) where the occupancy grid is occupied at `points` (N, S, 3), zero elsewhere:
        the occupied samples are gathered into one batch (each with its ray's per-ray inputs), evaluated,
        and scattered back. Without a grid, or with every sample occupied, field(samples, rays) itself.
        With none occupied, the field runs on one sample only to give the outputs' shapes (all zero)."""
        if self.occupancy_grid is None:
            return field(samples, rays)
        mask = self.occupancy_grid.occupied_at(points)
        if bool(mask.all()):
            return field(samples, rays)
        if not bool(mask.any()):
            probe = torch.zeros_like(mask)
            probe.view(-1)[0] = True
            shapes = field(*gather_samples(probe, samples, rays))
            return {k: v.new_zeros((*mask.shape, *v.shape[2:])) for k, v in shapes.items()}
        return scatter_samples(mask, field(*gather_samples(mask, samples, rays)))

    def mlp_for(self, level: int) -> nn.Module:
        return self.mlps[min(level, len(self.mlps) - 1)]

    def mlp_modules(self) -> dict[str, nn.Module]:
        """{label: module} of the distinct MLPs (a shared MLP appears once)."""
        if len(self.mlps) == 1:
            return {"mlp (coarse and fine, shared)": self.mlps[0]}
        return {f"{name} mlp": mlp for name, mlp in zip(LEVELS, self.mlps, strict=True)}

    def samples_per_level(self) -> tuple[int, int]:
        """(coarse, fine) intervals per ray."""
        fine = self.num_fine_samples + (self.num_coarse_samples if self.resample_padding is None else 0)
        return self.num_coarse_samples, fine

    def draw_noise(
        self, n_rays: int, like: Tensor, generator: torch.Generator | None = None
    ) -> dict[str, Tensor]:
        """The uniform draws one randomized `forward` of `n_rays` rays makes, per ray: {"coarse":
        (n_rays, S_c + 1) stratified jitter, "fine": (n_rays, n) resampling quantile jitter}, drawn in
        that order from `generator` (None: the global RNG of `like`'s device), in `like`'s dtype.

        `forward` draws exactly these when it is given none, so a batch's noise drawn up front and
        sliced per micro-batch (`noise=`) renders each ray as the whole batch would.
        """
        kind = {"dtype": like.dtype, "device": like.device, "generator": generator}
        coarse = torch.rand((n_rays, self.num_coarse_samples + 1), **kind)
        fine = torch.rand((n_rays, resample_draws(self.num_fine_samples, self.resample_padding)), **kind)
        return {"coarse": coarse, "fine": fine}

    def forward(
        self,
        rays: Rays,
        randomized: bool,
        generator: torch.Generator | None = None,
        noise: Mapping[str, Tensor] | None = None,
    ) -> list[dict[str, Tensor]]:
        """One dict per level (coarse, fine): rgb (N, 3), depth (N,), acc (N,), weights (N, S),
        tdist (N, S+1), and the model's extras. `randomized` jitters the samples (training), with
        `noise` (`draw_noise`) when given, else drawn here from `generator`."""
        if randomized and noise is None:
            noise = self.draw_noise(rays["near"].shape[0], rays["near"], generator)
        noise = noise if randomized else {}
        tdist = stratified_samples(
            rays["near"],
            rays["far"],
            self.num_coarse_samples,
            randomized,
            self.lindisp,
            generator,
            jitter=noise.get("coarse"),
        )
        outputs: list[dict[str, Tensor]] = []
        for level in range(len(LEVELS)):
            if level > 0:
                tdist = resample_tdist(
                    tdist,
                    outputs[-1]["weights"],
                    self.num_fine_samples,
                    randomized,
                    self.resample_padding,
                    generator,
                    jitter=noise.get("fine"),
                )
            # Under bf16 autocast the MLPs' outputs are bf16; compositing (transmittance products over
            # hundreds of samples) and the losses stay in fp32.
            fields = {k: at_least_fp32(v) for k, v in self.evaluate(level, rays, tdist).items()}
            weights, _, _ = compute_alpha_weights(
                fields["density"], tdist, rays["directions"], opaque_last=self.opaque_background
            )
            out = volumetric_rendering(fields["rgb"], weights, tdist, self.background.to(weights.dtype))
            out.update(weights=weights, tdist=tdist)
            out.update(self.level_extras(fields, weights, rays))
            outputs.append(out)
        return outputs

    def loss(self, outputs: list[dict[str, Tensor]], target_rgb: Tensor) -> tuple[Tensor, dict[str, float]]:
        """coarse_loss_mult * MSE_coarse + MSE_fine (+ the model's regularisers).

        The logged components are the unweighted per-level MSEs ('coarse', 'fine'; PSNR = -10 log10)
        and whatever `regularizers` adds; the returned tensor is the weighted total.
        """
        mses = [((out["rgb"] - target_rgb) ** 2).mean() for out in outputs]
        total = self.coarse_loss_mult * sum(mses[:-1]) + mses[-1]
        stats = {name: float(mse.detach()) for name, mse in zip(LEVELS, mses, strict=True)}
        reg, reg_stats = self.regularizers(outputs)
        if reg is not None:
            total = total + reg
        stats.update(reg_stats)
        return total, stats


class NeRF(NerfModelBase):
    """NeRF (Mildenhall et al. 2020): an encoding of each interval (`position_encoding`; NeRF's: the
    positional encoding, Eq. 4, of the midpoint o + t_mid d) and of the view direction (`view_encoding`,
    which reads a point: the unit direction); one MLP per level unless `single_mlp`."""

    name = "nerf"

    def __init__(
        self,
        coarse_mlp: NerfMLP,
        fine_mlp: NerfMLP | None,
        *,
        position_encoding: Encoding,
        view_encoding: Encoding,
        **base: Any,
    ) -> None:
        super().__init__(coarse_mlp, fine_mlp, **base)
        self.position_encoding, self.view_encoding = position_encoding, view_encoding

    def sample_inputs(self, rays: Rays, tdist: Tensor) -> tuple[Tensor, dict[str, Tensor]]:
        """(positions (N, S, 3), per-sample inputs of the position encoding) (`interval_inputs`)."""
        return interval_inputs(self.position_encoding.reads, rays, tdist)

    def encode_positions(self, samples: dict[str, Tensor]) -> Tensor:
        return self.position_encoding(**samples)

    def evaluate(self, level: int, rays: Rays, tdist: Tensor) -> dict[str, Tensor]:
        view_enc = self.view_encoding(rays["viewdirs"])
        mlp = self.mlp_for(level)
        points, samples = self.sample_inputs(rays, tdist)
        return self.evaluate_occupied(
            points, samples, {"view": view_enc}, lambda s, r: mlp(self.encode_positions(s), r["view"])
        )

    def point_density(self, points: Tensor) -> Tensor:
        """The density at points: the encoding of a point (a Gaussian of zero covariance for the IPE)."""
        return self.mlp_for(1).density(
            self.encode_positions(point_inputs(self.position_encoding.reads, points))
        )


class MipNeRF(NeRF):
    """mip-NeRF (Barron et al. 2021): NeRF's code with the integrated positional encoding (Eq. 14-16) of
    each interval's conical frustum Gaussian (Eq. 7-8) as its position encoding (conf/model/mipnerf.yaml);
    its own name, for the runs and reports."""

    name = "mipnerf"


class RefNeRF(NerfModelBase):
    """Ref-NeRF (Verbin et al. 2022) on mip-NeRF's sampling: `RefNerfMLP` per level (or shared).

    Extra outputs per level: rendered normals (normalize(sum_i w_i n_i)) and normals_pred, rendered
    roughness, and per sample: sample_normals, sample_normals_pred (N, S, 3); viewdirs (N, 3).

    Loss (Ref-NeRF Sec. 4), every term summed over levels with weight coarse_loss_mult on the coarse one:
        data + orientation_loss_mult * R_o + pred_normal_loss_mult * R_p,
        R_o = sum_i w_i max(0, n_i . d)^2          (Eq. 11; n: `orientation_normals` 'pred' (n') or
                                                  'density'; d: the view direction)
        R_p = sum_i w_i ||n_i - n'_i||^2            (Eq. 12),
    each averaged over rays. `orientation_stop_grad` stops the gradient of R_o through the weights.
    MLPs built with `density_normals=False` (multinerf's `disable_density_normals`) have no n: no rendered
    or per-sample normals, and R_p and R_o on n are undefined (the builder requires them off).
    """

    name = "refnerf"
    render_keys = ("rgb", "depth", "acc", "normals", "normals_pred")

    def __init__(
        self,
        coarse_mlp: RefNerfMLP,
        fine_mlp: RefNerfMLP | None,
        *,
        orientation_loss_mult: float = 0.1,
        pred_normal_loss_mult: float = 3e-4,
        orientation_normals: str = "pred",
        orientation_stop_grad: bool = False,
        **base: Any,
    ) -> None:
        super().__init__(coarse_mlp, fine_mlp, **base)
        if orientation_normals not in ORIENTATION_NORMALS:
            raise ValueError(f"orientation_normals: expected one of {list(ORIENTATION_NORMALS)}")
        self.orientation_loss_mult, self.pred_normal_loss_mult = orientation_loss_mult, pred_normal_loss_mult
        self.orientation_normals, self.orientation_stop_grad = orientation_normals, orientation_stop_grad
        self.density_normals = coarse_mlp.density_normals
        if not self.density_normals:
            self.render_keys = tuple(k for k in self.render_keys if k != "normals")

    def evaluate(self, level: int, rays: Rays, tdist: Tensor) -> dict[str, Tensor]:
        """The field on the intervals' inputs (Ref-NeRF's IPE: the Gaussians); with an occupancy grid, the
        normals (density gradient w.r.t. the positions) are those of the gathered samples, each of which
        depends on its own position only."""
        mlp = self.mlp_for(level)
        points, samples = interval_inputs(mlp.position_encoding.reads, rays, tdist)
        return self.evaluate_occupied(
            points, samples, {"viewdirs": rays["viewdirs"]}, lambda s, r: mlp(s, r["viewdirs"])
        )

    def point_density(self, points: Tensor) -> Tensor:
        """The density of a point: the spatial MLP on it (for the IPE: a Gaussian of zero covariance)."""
        mlp = self.mlp_for(1)
        return mlp.density(point_inputs(mlp.position_encoding.reads, points))

    def level_extras(self, fields: dict[str, Tensor], weights: Tensor, rays: Rays) -> dict[str, Tensor]:
        w = weights[..., None]
        extras = {
            "normals_pred": l2_normalize((w * fields["normals_pred"]).sum(dim=-2)),
            "roughness": (weights * fields["roughness"]).sum(dim=-1),
            "sample_normals_pred": fields["normals_pred"],
            "viewdirs": rays["viewdirs"],
        }
        if self.density_normals:
            extras["normals"] = l2_normalize((w * fields["normals"]).sum(dim=-2))
            extras["sample_normals"] = fields["normals"]
        return extras

    def regularizers(self, outputs: list[dict[str, Tensor]]) -> tuple[Tensor, dict[str, float]]:
        key = "sample_normals_pred" if self.orientation_normals == "pred" else "sample_normals"
        level_mults = [self.coarse_loss_mult] * (len(outputs) - 1) + [1.0]
        orientation, pred_normal = 0.0, 0.0
        for mult, out in zip(level_mults, outputs, strict=True):
            w = out["weights"]
            w_o = w.detach() if self.orientation_stop_grad else w
            n_dot_d = (out[key] * out["viewdirs"][..., None, :]).sum(dim=-1)
            orientation = orientation + mult * (w_o * torch.clamp(n_dot_d, min=0.0) ** 2).sum(dim=-1).mean()
            if self.density_normals:
                diff_sq = ((out["sample_normals"] - out["sample_normals_pred"]) ** 2).sum(dim=-1)
                pred_normal = pred_normal + mult * (w * diff_sq).sum(dim=-1).mean()
        total = self.orientation_loss_mult * orientation + self.pred_normal_loss_mult * pred_normal
        logged = {"orientation": float(orientation.detach())}
        if self.density_normals:
            logged["pred_normal"] = float(pred_normal.detach())
        return total, logged
