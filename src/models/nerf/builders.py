"""NeRF, mip-NeRF and Ref-NeRF built from their `model:` config groups (`_target_` in conf/model/*.yaml).

Each factory's keyword arguments are the group's keys (`src.models.instantiate.build_method` checks them
against the signature); the options all three share are one `TypedDict`, `FieldArgs`, unpacked into
`**common`, so that they are declared, typed and documented once. A size out of range is a one-line
`ConfigError` naming `model.<key>` (`model.occupancy_grid.<key>` for the grid's options).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal, NotRequired, TypedDict, Unpack

from torch import nn

from src.errors import ConfigError
from src.models.instantiate import at_least
from src.models.nerf.fields import ACTIVATIONS, NerfMLP, RefNerfMLP
from src.models.nerf.models import MipNeRF, NeRF, RefNeRF
from src.models.nerf.occupancy import OccupancyGrid

#: Ref-NeRF's integrated directional encoding uses degrees l = 1, 2, 4, ..., 2^(deg_view - 1) <= 16.
MAX_DEG_VIEW = 5


class FieldArgs(TypedDict):
    """Options of every NeRF-family model: positional encoding degrees, the MLP, and the sampling."""

    pos_min_deg: int  # positional encoding frequencies 2^pos_min_deg .. 2^(pos_max_deg - 1)
    pos_max_deg: int
    depth: int  # spatial MLP layers
    width: int
    skip_layer: int | None  # the input is concatenated after layer i > 0 with i % skip_layer == 0
    bottleneck_width: int
    view_depth: int  # view-dependent MLP layers
    view_width: int
    view_skip_layer: int | None
    density_activation: str  # a key of fields.ACTIVATIONS
    density_bias: float
    rgb_padding: float  # sigmoid(x) * (1 + 2 p) - p
    single_mlp: bool  # one MLP queried at both levels
    num_coarse_samples: int
    num_fine_samples: int
    resample_padding: float | None  # None: NeRF's importance sampling; else mip-NeRF's blurred resampling
    lindisp: bool  # coarse samples uniform in 1/t
    coarse_loss_mult: float
    background: Sequence[float]  # RGB behind each ray
    # NeRF's released code: the last interval is 1e10 long, so a ray is opaque at the far bound
    # (absent in configs from before the option: False, the real interval of mip-NeRF / multinerf)
    opaque_background: NotRequired[bool]
    # Empty-space skipping (`occupancy.OccupancyGrid`): None (every sample evaluated) or a mapping of
    # every argument of OccupancyGrid (absent in configs from before the option: None)
    occupancy_grid: NotRequired[Mapping[str, Any] | None]


def _degrees(prefix: str, lo: int, hi: int) -> tuple[int, int]:
    at_least(f"{prefix}_min_deg", lo, 0)
    if hi <= lo:
        raise ConfigError(f"model.{prefix}_max_deg: expected > {prefix}_min_deg ({lo}), got {hi}")
    return lo, hi


def _trunk(common: FieldArgs) -> dict:
    """The MLP options, checked."""
    if common["density_activation"] not in ACTIVATIONS:
        found = common["density_activation"]
        raise ConfigError(f"model.density_activation: unknown {found!r}; expected one of {list(ACTIVATIONS)}")
    for key, minimum in (
        ("depth", 1),
        ("width", 1),
        ("bottleneck_width", 1),
        ("view_depth", 0),
        ("view_width", 1),
    ):
        at_least(key, common[key], minimum)
    for key in ("skip_layer", "view_skip_layer"):
        if common[key] is not None:
            at_least(key, common[key], 0)
    at_least("rgb_padding", common["rgb_padding"], 0.0)
    keys = ("depth", "width", "skip_layer", "bottleneck_width", "view_depth", "view_width", "view_skip_layer")
    return {k: common[k] for k in (*keys, "density_activation", "density_bias", "rgb_padding")}


def _rendering(common: FieldArgs) -> dict:
    """The two-level rendering options (`NerfModelBase`), checked."""
    at_least("num_coarse_samples", common["num_coarse_samples"], 1)
    at_least("num_fine_samples", common["num_fine_samples"], 1)
    at_least("coarse_loss_mult", common["coarse_loss_mult"], 0.0)
    if common["resample_padding"] is not None:
        at_least("resample_padding", common["resample_padding"], 0.0)
    background = common["background"]
    if (
        not isinstance(background, Sequence)
        or len(background) != 3
        or not all(isinstance(c, int | float) and not isinstance(c, bool) for c in background)
    ):
        raise ConfigError(f"model.background: expected 3 numbers (RGB), got {background!r}")
    keys = ("num_coarse_samples", "num_fine_samples", "resample_padding", "lindisp", "coarse_loss_mult")
    opaque = common.get("opaque_background", False)  # typed (bool) by build_method
    return {
        **{k: common[k] for k in keys},
        "background": tuple(float(c) for c in background),
        "opaque_background": opaque,
        "occupancy_grid": occupancy_grid(common.get("occupancy_grid")),
    }


#: The keys of `model.occupancy_grid`, and the check of each value (None: any bool).
GRID_KEYS: dict[str, tuple[type, float | None]] = {
    "aabb": (list, None),
    "resolution": (int, 1),
    "update_every": (int, 1),
    "decay": (float, 0.0),
    "threshold": (float, 0.0),
    "warmup_steps": (int, 0),
    "sample_fraction": (float, 0.0),
    "occupied_outside": (bool, None),
    "chunk": (int, 1),
}


def occupancy_grid(cfg: Mapping[str, Any] | None) -> OccupancyGrid | None:
    """The `model.occupancy_grid` mapping as an `OccupancyGrid` (None: None), every key given and checked:
    a missing, unknown or out-of-range value is a one-line ConfigError naming `model.occupancy_grid.<key>`."""
    if cfg is None:
        return None
    if not isinstance(cfg, Mapping):
        expected = f"expected null or a mapping of {list(GRID_KEYS)}"
        raise ConfigError(f"model.occupancy_grid: {expected}, got {cfg!r}")
    for key in cfg:
        if key not in GRID_KEYS:
            raise ConfigError(f"model.occupancy_grid.{key}: unknown key; expected one of {list(GRID_KEYS)}")
    for key, (kind, minimum) in GRID_KEYS.items():
        name = f"model.occupancy_grid.{key}"
        if key not in cfg:
            raise ConfigError(f"{name}: missing")
        value = cfg[key]
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if kind is bool and not isinstance(value, bool):
            raise ConfigError(f"{name}: expected true or false, got {value!r}")
        if kind is int and not (number and value == int(value)):
            raise ConfigError(f"{name}: expected an integer, got {value!r}")
        if kind is float and not number:
            raise ConfigError(f"{name}: expected a number, got {value!r}")
        if minimum is not None and value < minimum:
            raise ConfigError(f"{name}: expected >= {minimum}, got {value!r}")
    if not 0.0 < cfg["decay"] <= 1.0 or not 0.0 < cfg["sample_fraction"] <= 1.0:
        key = "decay" if not 0.0 < cfg["decay"] <= 1.0 else "sample_fraction"
        raise ConfigError(f"model.occupancy_grid.{key}: expected a number in (0, 1], got {cfg[key]!r}")
    aabb = cfg["aabb"]
    if (
        not isinstance(aabb, Sequence)
        or len(aabb) != 6
        or not all(isinstance(c, int | float) and not isinstance(c, bool) for c in aabb)
        or not all(aabb[i] < aabb[i + 3] for i in range(3))
    ):
        raise ConfigError(
            f"model.occupancy_grid.aabb: expected [x_min, y_min, z_min, x_max, y_max, z_max] with each "
            f"min < max, got {aabb!r}"
        )
    return OccupancyGrid(**{k: (int(v) if GRID_KEYS[k][0] is int else v) for k, v in cfg.items()})


def _levels(single_mlp: bool, make: Callable[[], nn.Module]) -> tuple[nn.Module, nn.Module | None]:
    """(coarse MLP, fine MLP or None when one MLP serves both levels)."""
    coarse = make()
    return coarse, (None if single_mlp else make())


def _pe_model(cls: type[NeRF], pos_identity: bool, view: tuple[int, int, bool], common: FieldArgs) -> NeRF:
    pos_deg = _degrees("pos", common["pos_min_deg"], common["pos_max_deg"])
    view_deg, view_identity = _degrees("view", view[0], view[1]), view[2]
    pos_dim = 3 * (2 * (pos_deg[1] - pos_deg[0]) + pos_identity)
    view_dim = 3 * (2 * (view_deg[1] - view_deg[0]) + view_identity)
    trunk = _trunk(common)
    coarse, fine = _levels(common["single_mlp"], lambda: NerfMLP(pos_dim, view_dim, **trunk))
    return cls(
        coarse,
        fine,
        pos_deg=pos_deg,
        pos_identity=pos_identity,
        view_deg=view_deg,
        view_identity=view_identity,
        **_rendering(common),
    )


def nerf_model(
    *,
    pos_identity: bool,
    view_min_deg: int,
    view_max_deg: int,
    view_identity: bool,
    **common: Unpack[FieldArgs],
) -> NeRF:
    """NeRF (Mildenhall et al. 2020): positional encoding of points (with the point itself when
    `pos_identity`) and of the view direction."""
    return _pe_model(NeRF, pos_identity, (view_min_deg, view_max_deg, view_identity), common)


def mipnerf_model(
    *, view_min_deg: int, view_max_deg: int, view_identity: bool, **common: Unpack[FieldArgs]
) -> MipNeRF:
    """mip-NeRF (Barron et al. 2021): the integrated positional encoding of conical frustums (which has no
    identity term)."""
    return _pe_model(MipNeRF, False, (view_min_deg, view_max_deg, view_identity), common)


def _check_without_density_normals(pred_normal_loss_mult: float, orientation_normals: str) -> None:
    """Without density normals n, R_p (Eq. 12: n against n') and R_o on n do not exist."""
    if pred_normal_loss_mult != 0:
        raise ConfigError(
            "model.pred_normal_loss_mult: R_p compares the density-gradient normals, which "
            f"model.density_normals=false leaves out; expected 0, got {pred_normal_loss_mult}"
        )
    if orientation_normals != "pred":
        raise ConfigError(
            "model.orientation_normals: model.density_normals=false leaves out the density-gradient "
            f"normals; expected 'pred', got {orientation_normals!r}"
        )


def refnerf_model(
    *,
    deg_view: int,
    roughness_bias: float,
    orientation_loss_mult: float,
    pred_normal_loss_mult: float,
    orientation_normals: Literal["pred", "density"],
    orientation_stop_grad: bool,
    density_normals: bool = True,
    **common: Unpack[FieldArgs],
) -> RefNeRF:
    """Ref-NeRF (Verbin et al. 2022): mip-NeRF's sampling and IPE, the integrated directional encoding of
    the reflected view direction, and the orientation / predicted-normal regularisers.
    `density_normals=False` (multinerf's `disable_density_normals`) leaves out the density-gradient normals
    and so needs the regularisers that read them off."""
    pos_deg = _degrees("pos", common["pos_min_deg"], common["pos_max_deg"])
    if not 1 <= deg_view <= MAX_DEG_VIEW:
        raise ConfigError(
            f"model.deg_view: expected an integer in [1, {MAX_DEG_VIEW}] (l <= 16), got {deg_view}"
        )
    at_least("orientation_loss_mult", orientation_loss_mult, 0.0)
    at_least("pred_normal_loss_mult", pred_normal_loss_mult, 0.0)
    if not density_normals:
        _check_without_density_normals(pred_normal_loss_mult, orientation_normals)
    mlp = {
        **_trunk(common),
        "min_deg_point": pos_deg[0],
        "max_deg_point": pos_deg[1],
        "deg_view": deg_view,
        "roughness_bias": roughness_bias,
        "density_normals": density_normals,
    }
    coarse, fine = _levels(common["single_mlp"], lambda: RefNerfMLP(**mlp))
    return RefNeRF(
        coarse,
        fine,
        orientation_loss_mult=orientation_loss_mult,
        pred_normal_loss_mult=pred_normal_loss_mult,
        orientation_normals=orientation_normals,
        orientation_stop_grad=orientation_stop_grad,
        **_rendering(common),
    )
