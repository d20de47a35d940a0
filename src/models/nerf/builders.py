"""NeRF, mip-NeRF and Ref-NeRF built from their `model:` config groups (`_target_` in conf/model/*.yaml).

Each factory's keyword arguments are the group's keys (`src.models.instantiate.build_method` checks them
against the signature); the options all three share are one `TypedDict`, `FieldArgs`, unpacked into
`**common`, so that they are declared, typed and documented once. A size out of range is a one-line
`ConfigError` naming `model.<key>` (`model.occupancy_grid.<key>` for the grid's options).

The encodings are `_target_` sub-configs, `model.position_encoding` and `model.view_encoding`
(conf/encoding/), each built into an `encodings.Encoding` by `build_encoding`; the MLPs' input sizes are
the encodings' `out_dim`. A `_target_` that is not an encoding, an argument it does not take, a value it
rejects, or an encoding that reads the wrong input for its place is a one-line `ConfigError` naming
`model.<position|view>_encoding[.<key>]`.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Any, Literal, NotRequired, TypedDict, Unpack

from torch import nn

from src.errors import ConfigError, one_line
from src.models.instantiate import TARGET_KEY, arguments_of, at_least, check_arguments, resolve_target
from src.models.nerf.encodings import Encoding
from src.models.nerf.fields import ACTIVATIONS, NerfMLP, RefNerfMLP
from src.models.nerf.models import MipNeRF, NeRF, RefNeRF
from src.models.nerf.occupancy import OccupancyGrid

#: What the encoding at each place may read (`encodings.READS`): a position encoding a point (the interval
#: midpoint) or a Gaussian (the conical frustum); NeRF's view encoding the unit view direction (a point);
#: Ref-NeRF's a von Mises-Fisher lobe (the reflected direction and the roughness).
POSITION_READS = ("point", "gaussian")
NERF_VIEW_READS = ("point",)
REFNERF_VIEW_READS = ("vmf",)


class FieldArgs(TypedDict):
    """Options of every NeRF-family model: the encodings, the MLP, and the sampling."""

    # `_target_` sub-configs of encodings.Encoding subclasses, built by `build_encoding` (conf/encoding/)
    position_encoding: Mapping[str, Any]
    view_encoding: Mapping[str, Any]
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


def build_encoding(key: str, cfg: Any, reads: tuple[str, ...]) -> Encoding:
    """The encoding `model.<key>` configures: its `_target_` (a subclass of `encodings.Encoding`) called
    with the other keys, checked like a method's (`instantiate.check_arguments`), and reading one of
    `reads`. Every failure is a one-line ConfigError naming `model.<key>` or `model.<key>.<argument>`."""
    section = f"model.{key}"
    if not isinstance(cfg, Mapping):
        raise ConfigError(f"{section}: expected a mapping with {TARGET_KEY} (an encoding class), got {cfg!r}")
    target = resolve_target(cfg, section)  # a missing or unimportable _target_ is its one-line error
    name = getattr(target, "__qualname__", repr(target))
    if not (isinstance(target, type) and issubclass(target, Encoding)):
        raise ConfigError(
            f"{section}.{TARGET_KEY}: {cfg[TARGET_KEY]!r} is not an encoding; expected a subclass of "
            "src.models.nerf.encodings.Encoding"
        )
    kwargs = {k: v for k, v in cfg.items() if k != TARGET_KEY}
    arguments = arguments_of(target)
    check_arguments(target, arguments, kwargs, set(), section=section)
    try:
        encoding = target(**kwargs)
    except (TypeError, ValueError) as err:  # the class's own range checks, "<argument>: ..."
        message = one_line(err)
        argument, colon, rest = message.partition(":")
        if colon and argument in arguments[0]:
            raise ConfigError(f"{section}.{argument}:{rest}") from None
        raise ConfigError(f"{section} ({name}): {message}") from None
    out_dim = getattr(encoding, "out_dim", None)
    if not isinstance(out_dim, int) or isinstance(out_dim, bool) or out_dim < 1:
        raise ConfigError(f"{section}.{TARGET_KEY}: {name} sets no out_dim (a positive int), got {out_dim!r}")
    if getattr(encoding, "reads", None) not in reads:
        raise ConfigError(
            f"{section}.{TARGET_KEY}: {name} reads {getattr(encoding, 'reads', None)!r}; expected an "
            f"encoding that reads one of {list(reads)} here"
        )
    return encoding


#: The flat encoding keys of the configs from before the encodings were `_target_` sub-configs.
LEGACY_ENCODING_KEYS = (
    "pos_min_deg",
    "pos_max_deg",
    "pos_identity",
    "view_min_deg",
    "view_max_deg",
    "view_identity",
    "deg_view",
)


def upgrade_legacy_encodings(cfg: Mapping[str, Any]) -> dict[str, Any]:
    """A NeRF-family model config in today's keys: one from before the encodings were sub-configs
    (`pos_min_deg`, `pos_max_deg`, `pos_identity` / `view_*` / `deg_view` of `nerf_model`,
    `mipnerf_model`, `refnerf_model`) gets the `position_encoding` and `view_encoding` that build the same
    network, so that its checkpoints still load; any other config is returned as it is."""
    target = str(cfg.get(TARGET_KEY, ""))
    builder = target.rsplit(".", 1)[-1]
    if "pos_max_deg" not in cfg or builder not in ("nerf_model", "mipnerf_model", "refnerf_model"):
        return dict(cfg)
    module = Encoding.__module__
    degrees = {"min_deg": cfg["pos_min_deg"], "max_deg": cfg["pos_max_deg"]}
    if builder == "nerf_model":
        position = {TARGET_KEY: f"{module}.PositionalEncoding", **degrees, "identity": cfg["pos_identity"]}
    else:
        position = {TARGET_KEY: f"{module}.IntegratedPositionalEncoding", **degrees}
    if builder == "refnerf_model":
        view = {TARGET_KEY: f"{module}.IntegratedDirectionalEncoding", "deg_view": cfg["deg_view"]}
    else:
        view = {
            TARGET_KEY: f"{module}.PositionalEncoding",
            "min_deg": cfg["view_min_deg"],
            "max_deg": cfg["view_max_deg"],
            "identity": cfg["view_identity"],
        }
    rest = {k: v for k, v in cfg.items() if k not in LEGACY_ENCODING_KEYS}
    return {**rest, "position_encoding": position, "view_encoding": view}


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


def _pe_model(cls: type[NeRF], common: FieldArgs) -> NeRF:
    position = build_encoding("position_encoding", common["position_encoding"], POSITION_READS)
    view = build_encoding("view_encoding", common["view_encoding"], NERF_VIEW_READS)
    trunk = _trunk(common)
    coarse, fine = _levels(common["single_mlp"], lambda: NerfMLP(position.out_dim, view.out_dim, **trunk))
    return cls(coarse, fine, position_encoding=position, view_encoding=view, **_rendering(common))


def nerf_model(**common: Unpack[FieldArgs]) -> NeRF:
    """NeRF (Mildenhall et al. 2020): its configs encode the interval midpoints and the view direction with
    the positional encoding (Eq. 4)."""
    return _pe_model(NeRF, common)


def mipnerf_model(**common: Unpack[FieldArgs]) -> MipNeRF:
    """mip-NeRF (Barron et al. 2021): its configs encode the conical frustums with the integrated positional
    encoding (Eq. 14-16) and the view direction with NeRF's PE."""
    return _pe_model(MipNeRF, common)


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
    roughness_bias: float,
    orientation_loss_mult: float,
    pred_normal_loss_mult: float,
    orientation_normals: Literal["pred", "density"],
    orientation_stop_grad: bool,
    density_normals: bool = True,
    **common: Unpack[FieldArgs],
) -> RefNeRF:
    """Ref-NeRF (Verbin et al. 2022): mip-NeRF's sampling and (in its config) IPE, an encoding of the
    reflected view direction that reads a vMF lobe (its config: the integrated directional encoding), and
    the orientation / predicted-normal regularisers.
    `density_normals=False` (multinerf's `disable_density_normals`) leaves out the density-gradient normals
    and so needs the regularisers that read them off."""
    position = build_encoding("position_encoding", common["position_encoding"], POSITION_READS)
    view = build_encoding("view_encoding", common["view_encoding"], REFNERF_VIEW_READS)
    at_least("orientation_loss_mult", orientation_loss_mult, 0.0)
    at_least("pred_normal_loss_mult", pred_normal_loss_mult, 0.0)
    if not density_normals:
        _check_without_density_normals(pred_normal_loss_mult, orientation_normals)
    mlp = {
        **_trunk(common),
        "position_encoding": position,
        "view_encoding": view,
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
