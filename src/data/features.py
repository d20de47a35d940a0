"""Which auxiliary features a denoiser sees, chosen by configuration (`task.features`).

A feature is a buffer's value (`albedo`), its one-channel Monte Carlo variance (`albedo.var`) or its
image gradients (`albedo.grad`: `image_gradients`, all x channels then all y channels); the buffers are
the branch's transformed colour and the surface guides of the first hit. Preprocessing stores every
candidate (`CANDIDATE_FEATURES`, 38 channels per branch) once; a run selects its channels from them by
name, so a feature ablation needs no new preprocessing, and channel counts (a model's `in_channels`) are
derived from the list, never typed by hand.

`task.features` is a list; channels follow the order written (a list, not a mapping, so that a command
line override such as `task.features=[color,albedo,normal]` replaces it rather than merging into it).
`PAPER_FEATURES` is the 28-channel set of Bako et al. 2017, Sec. 4.1, and of the seed thesis (Bunjevac
2019, Sec. 4.3): the colour with its variance and gradients, the variances and gradients of normal and
albedo, depth with its variance and gradients.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from src.errors import ConfigError, DataError

#: Feature buffers and their channel suffixes. "color" is the branch's transformed colour
#: (diffuse / (albedo + eps), or log(1 + specular)); depth is normalised to [0, 1] per image; visibility
#: is the direct-light visibility of the first hit (1 unoccluded, 0 shadowed).
FEATURE_BUFFERS: Mapping[str, tuple[str, ...]] = {
    "color": ("r", "g", "b"),
    "normal": ("x", "y", "z"),
    "depth": ("z",),
    "albedo": ("r", "g", "b"),
    "visibility": ("v",),
}
#: What a feature entry may add after the buffer name ("albedo.var"); the bare name is the value.
COMPONENTS = ("var", "grad")
#: Where the setting lives, for error messages.
FEATURES_KEY = "task.features"

Features = Sequence[str]

PAPER_FEATURES: Features = (
    *("color", "color.var", "color.grad"),
    *("normal.var", "normal.grad"),
    *("depth", "depth.var", "depth.grad"),
    *("albedo.var", "albedo.grad"),
)
#: Every feature preprocessing stores, in storage order.
CANDIDATE_FEATURES: Features = tuple(
    f"{buffer}{suffix}" for buffer in FEATURE_BUFFERS for suffix in ("", ".var", ".grad")
)


def _channels(feature: str) -> tuple[str, ...]:
    """Channel names of one feature: `color_r`.. or `depth` (value), `color_var` (variance),
    `color_dx_r`.. `color_dy_b` (gradients)."""
    buffer, _, component = feature.partition(".")
    suffixes = FEATURE_BUFFERS[buffer]
    if component == "var":
        return (f"{buffer}_var",)
    if component == "grad":
        return tuple(f"{buffer}_d{axis}_{c}" for axis in "xy" for c in suffixes)
    return (buffer,) if len(suffixes) == 1 else tuple(f"{buffer}_{c}" for c in suffixes)


def _check(features: Features) -> None:
    example = "e.g. [color, color.var, color.grad, albedo]"
    if isinstance(features, str | Mapping) or not isinstance(features, Sequence) or not features:
        raise ConfigError(f"{FEATURES_KEY}={features!r}: expected a non-empty list of features, {example}")
    for i, feature in enumerate(features):
        buffer, dot, component = str(feature).partition(".")
        if buffer not in FEATURE_BUFFERS or (dot and component not in COMPONENTS):
            raise ConfigError(
                f"{FEATURES_KEY}[{i}]={feature!r}: expected a buffer of {list(FEATURE_BUFFERS)}, "
                f"optionally with .var or .grad"
            )
    check_no_repeats(features, FEATURES_KEY)


def check_no_repeats(features: Features, key: str) -> None:
    """A one-line ConfigError naming `key` when a feature list names a feature more than once."""
    duplicates = sorted({str(f) for f in features if list(features).count(f) > 1})
    if duplicates:
        raise ConfigError(f"{key}: {duplicates} listed more than once")


def feature_channels(features: Features) -> tuple[str, ...]:
    """The channel names `features` selects, in order; a one-line ConfigError for an unknown buffer or
    component or a repeated feature."""
    _check(features)
    return tuple(name for feature in features for name in _channels(str(feature)))


def feature_count(features: Features) -> int:
    """Number of input channels per branch (the `${nrbench.channels:${task.features}}` resolver)."""
    return len(feature_channels(features))


CANDIDATE_CHANNELS = feature_channels(CANDIDATE_FEATURES)
PAPER_CHANNELS = feature_channels(PAPER_FEATURES)
assert len(CANDIDATE_CHANNELS) == 38 and len(PAPER_CHANNELS) == 28


def channel_indices(
    selected: Sequence[str],
    stored: Sequence[str],
    where: str,
    key: str = FEATURES_KEY,
    rerun: str = "run stage=preprocess again to store every candidate feature",
) -> list[int]:
    """Positions of the `selected` channel names in `stored` (what a prepared folder holds); a one-line
    error naming `where` and the config `key` if the data lack one (prepared by an older version: the
    `rerun` advice)."""
    position = {name: i for i, name in enumerate(stored)}
    missing = [name for name in selected if name not in position]
    if missing:
        raise DataError(f"{where}: no channel {missing[0]!r} for {key} ({len(missing)} missing); {rerun}")
    return [position[name] for name in selected]


def input_features(cfg) -> list[str]:
    """`task.features` of a run config as plain data (what a checkpoint records)."""
    return [str(feature) for feature in cfg.task.features]


def check_trained_features(trained: Features | None, configured: Features, checkpoint: str) -> None:
    """A checkpoint's model saw the configured channels (checkpoints that predate `task.features` were
    all trained on the paper set)."""
    trained_channels = feature_channels(trained or PAPER_FEATURES)
    if trained_channels != feature_channels(configured):
        raise DataError(
            f"{checkpoint}: trained with {FEATURES_KEY}=[{','.join(trained or PAPER_FEATURES)}], "
            f"configured [{','.join(configured)}]; evaluate with the features it was trained on"
        )
