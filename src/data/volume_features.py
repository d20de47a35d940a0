"""The volumetric denoiser's candidate input channels and how a run selects some of them by name
(`dataset.volume_features`), the volumetric counterpart of `src.data.features` (issue 16).

Preprocessing (`src.data.volume_shards`) stores every candidate once per frame; a run picks its channels
by name at load time, so a feature ablation needs no new preprocessing and channel counts are derived
from the list. A feature is a buffer's value (`sigma_t`) or its one-channel Monte Carlo variance of the
pixel mean (`sigma_t.var`). The buffers are those of the volumetric path tracer
(`src.data.volume_aovs.VOLUME_BUFFERS`, with `color` first) except the raw world-space points
`position` and `scatter_position` (not translation invariant: a network would learn the scenes'
coordinates; they served to compute `motion`), plus `motion` (screen-space flow in pixels, no variance).

Each buffer's value is stored under the transform of its `VALUE_KINDS` kind, its variance propagated
to first order (`src.data.volume_shards.transform_pair`):

* `radiance` (`color`, `surface`, `volume`, `volume_single`, `volume_multi`): `task.preprocess.
  volume_transform` (`log_modulus` by default, Zhu et al. 2023's input transform; `none`: linear);
* `unbounded` (`optical_thickness` (up to 1000), `sigma_t`, `sigma_s`, `volume_events`: non-negative,
  heavy-tailed): the same transform, so `none` gives a fully linear ablation;
* `distance` (`depth`, `scatter_depth`, `scatter_media_distance`): divided by one scale per sequence,
  the maximum of the three over all its frames (Bako et al.'s per-image depth normalisation, per
  sequence so that it does not flicker, and shared so that scatter_depth / depth is kept);
* `as_is`: bounded buffers (`albedo`, `normal`, `visibility`, `transmittance`, `scatter_albedo`,
  `scattered`) and `motion` (pixels, signed: a model warps with it).

No image gradients are stored (unlike the KPCN candidates): the volumetric denoiser is a U-Net, whose
first convolution sees neighbouring pixels anyway, and x and y gradients of the 42 value channels
would add 84 channels per frame (+135 %).

`dataset.volume_features` is a list (channels in the order written) or null, every candidate in storage
order (`VOLUME_CANDIDATE_FEATURES`, 62 channels).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from types import MappingProxyType

from src.data.features import channel_indices, check_no_repeats
from src.data.volume_aovs import CHANNEL_COUNT
from src.errors import ConfigError

#: Where the setting lives, for error messages.
VOLUME_FEATURES_KEY = "dataset.volume_features"
#: Raw world-space points: rendered, never network inputs.
DROPPED_BUFFERS = ("position", "scatter_position")
#: Buffers whose per-channel names use x/y/z rather than r/g/b.
_VECTOR_BUFFERS = ("normal",)

VALUE_KINDS: Mapping[str, str] = MappingProxyType(
    {
        **dict.fromkeys(("color", "surface", "volume", "volume_single", "volume_multi"), "radiance"),
        **dict.fromkeys(("optical_thickness", "sigma_t", "sigma_s", "volume_events"), "unbounded"),
        **dict.fromkeys(("depth", "scatter_depth", "scatter_media_distance"), "distance"),
        **dict.fromkeys(
            ("albedo", "normal", "visibility", "transmittance", "scatter_albedo", "scattered", "motion"),
            "as_is",
        ),
    }
)


def _suffixes(buffer: str, n: int) -> tuple[str, ...]:
    if n == 1:
        return ("",)
    if buffer == "motion":
        return ("x", "y")
    return ("x", "y", "z") if buffer in _VECTOR_BUFFERS else ("r", "g", "b")


#: Feature buffers (every rendered buffer but the world-space points, then `motion`) and their channel
#: suffixes ("" for one-channel buffers).
VOLUME_FEATURE_BUFFERS: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        **{b: _suffixes(b, n) for b, n in CHANNEL_COUNT.items() if b not in DROPPED_BUFFERS},
        "motion": ("x", "y"),
    }
)
assert set(VOLUME_FEATURE_BUFFERS) == set(VALUE_KINDS), "every volumetric feature buffer needs a kind"
#: Buffers without a variance feature.
NO_VARIANCE = ("motion",)

Features = Sequence[str]

#: Every feature preprocessing stores, in storage order: each buffer's value, then its variance.
VOLUME_CANDIDATE_FEATURES: Features = tuple(
    f"{buffer}{suffix}"
    for buffer in VOLUME_FEATURE_BUFFERS
    for suffix in (("",) if buffer in NO_VARIANCE else ("", ".var"))
)


def _channels(feature: str) -> tuple[str, ...]:
    """Channel names of one feature: `color_r`.. or `depth` (value), `color_var` (variance)."""
    buffer, _, component = feature.partition(".")
    if component == "var":
        return (f"{buffer}_var",)
    return tuple(f"{buffer}_{s}" if s else buffer for s in VOLUME_FEATURE_BUFFERS[buffer])


def _check(features: Features) -> None:
    example = "e.g. [color, color.var, albedo, normal, depth, transmittance, motion], or null for all"
    if isinstance(features, str | Mapping) or not isinstance(features, Sequence) or not features:
        raise ConfigError(
            f"{VOLUME_FEATURES_KEY}={features!r}: expected a non-empty list of features, {example}"
        )
    for i, feature in enumerate(features):
        buffer, dot, component = str(feature).partition(".")
        known = buffer in VOLUME_FEATURE_BUFFERS and (
            not dot or (component == "var" and buffer not in NO_VARIANCE)
        )
        if not known:
            raise ConfigError(
                f"{VOLUME_FEATURES_KEY}[{i}]={feature!r}: expected a buffer of "
                f"{list(VOLUME_FEATURE_BUFFERS)}, optionally with .var (not motion)"
            )
    check_no_repeats(features, VOLUME_FEATURES_KEY)


def volume_feature_channels(features: Features | None) -> tuple[str, ...]:
    """The channel names `features` selects, in order (None: every candidate); a one-line ConfigError
    naming `dataset.volume_features` for an unknown buffer, a variance of motion or a repeated feature."""
    if features is None:
        features = VOLUME_CANDIDATE_FEATURES
    _check(features)
    return tuple(name for feature in features for name in _channels(str(feature)))


def volume_feature_count(features: Features | None) -> int:
    """Number of input channels per frame (the `${nrbench.volume_channels:${dataset.volume_features}}`
    resolver)."""
    return len(volume_feature_channels(features))


VOLUME_CANDIDATE_CHANNELS = volume_feature_channels(VOLUME_CANDIDATE_FEATURES)
assert len(VOLUME_CANDIDATE_CHANNELS) == 62


def volume_channel_indices(selected: Sequence[str], stored: Sequence[str], where: str) -> list[int]:
    """Positions of the `selected` channel names in `stored`; a one-line DataError naming `where` if the
    prepared data lack one (prepared by an older version: preprocess again)."""
    rerun = "run stage=preprocess dataset=volumetric again to store every candidate"
    return channel_indices(selected, stored, where, VOLUME_FEATURES_KEY, rerun)
