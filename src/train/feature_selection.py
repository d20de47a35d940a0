"""Pure building blocks of automatic auxiliary-feature selection for a Monte Carlo denoiser.

After Zhang, Manzi, Vogels et al. 2022 (feature selection for Monte Carlo denoisers), as used for the
volumetric denoiser of the Pixar/Disney 2023 talk "Denoising Production Volumetric Rendering":

1. train one *probe* denoiser on every candidate feature (`dataset.volume_features`), each training sample
   keeping a random subset of the candidates (`keep_mask`, `drop_features`): a dropped feature's
   channels are set to its neutral value (0 by default, transmittance 1: "no medium"; `neutral_values`),
   so the probe learns to denoise from any subset. `dataset.feature_selection.subsets` says how a subset is
   drawn: `uniform_size` (the default) draws the number kept, k, uniformly from 0..n (n candidates
   besides the always-kept colour), then a uniform subset of that size (`uniform_size_keep_mask`);
   `independent` (the ablation, and the scheme of runs before it) drops each candidate independently
   with probability `dropout` (`random_keep_mask`). Step 2 scores the probe on subsets of every size
   (1, 2, ... n candidates), so it must train on every size: under `independent` the count kept is
   Binomial(n, 1 - p), and at n = 35, p = 0.5 a subset of <= 4 is drawn with probability 1.7e-6 per
   sample, all 35 with 2.9e-11, i.e. never; the greedy curve then came out U-shaped (an untrained
   probe's too), measuring the probe's unfamiliarity with a subset size, not the features. Under
   `uniform_size` each size is 1 / (n + 1) of the samples, each subset of size k 1 / C(n, k) of those;
2. greedy forward selection (`greedy_forward_selection`): starting from a start set (the colour), add
   at each round the candidate whose addition lowers the probe's validation loss most, the features
   not selected set to their neutral values (`keep_only`), with NO retraining; this gives the
   loss-vs-feature-count curve and the ordered feature list;
3. train final denoisers on the first `size` features of that list (`src.data.feature_choice`) and, as the
   study's baseline arm, on the same number chosen at random (`random_features`).

Neutral values are in the space of the inputs the probe sees (after the value transform and, when the
run whitens, after whitening): the caller passes them in that space. A variance feature's neutral value
is 0 (no noise) unless overridden by its full name (`albedo.var`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping, Sequence

import torch
from tqdm import tqdm

from src.data.feature_choice import FEATURE_SELECTION_KEY, remaining_candidates
from src.data.volume_features import (
    VOLUME_CANDIDATE_FEATURES,
    VOLUME_FEATURE_BUFFERS,
    Features,
    volume_feature_channels,
)
from src.errors import ConfigError

#: Where the settings live, for error messages.
NEUTRAL_KEY = f"{FEATURE_SELECTION_KEY}.neutral"
P_DROP_KEY = f"{FEATURE_SELECTION_KEY}.dropout"
SUBSETS_KEY = f"{FEATURE_SELECTION_KEY}.subsets"
#: How the probe draws a training sample's subset (`dataset.feature_selection.subsets`; `keep_mask`).
SUBSETS = ("uniform_size", "independent")

#: One row of the greedy selection: round, the feature added (None in round 0), the ordered selection so
#: far (start set included) and its validation loss.
Row = dict


def feature_slices(features: Features) -> list[tuple[str, slice]]:
    """Each feature's channel range within the input tensor built from `features` (in that order), e.g.
    `[("color", slice(0, 3)), ("color.var", slice(3, 4)), ...]`."""
    out, start = [], 0
    for feature in features:
        n = len(volume_feature_channels([feature]))
        out.append((str(feature), slice(start, start + n)))
        start += n
    return out


def neutral_values(features: Features, neutral: Mapping[str, float] | None = None) -> torch.Tensor:
    """Per-channel neutral value (C,) of the inputs built from `features`: `neutral[feature]` for each
    feature listed there, 0 for the others. A key is a feature name: a buffer name (`transmittance`,
    `visibility`) is that buffer's value, `<buffer>.var` its variance. A key that names no candidate
    feature: a one-line ConfigError naming `dataset.feature_selection.neutral`."""
    neutral = dict(neutral or {})
    unknown = sorted(str(k) for k in neutral if k not in VOLUME_CANDIDATE_FEATURES)
    if unknown:
        raise ConfigError(
            f"{NEUTRAL_KEY}: unknown features {unknown}; expected a buffer of {list(VOLUME_FEATURE_BUFFERS)}"
            " or <buffer>.var"
        )
    slices = feature_slices(features)
    values = torch.zeros(slices[-1][1].stop if slices else 0)
    for feature, s in slices:
        values[s] = float(neutral.get(feature, 0.0))
    return values


def random_keep_mask(
    n: int,
    n_features: int,
    p_drop: float,
    generator: torch.Generator | None = None,
    always_keep: Sequence[int] = (),
) -> torch.Tensor:
    """A (n, n_features) bool mask, True = keep: each feature of each sample dropped independently with
    probability `p_drop`, the features at indices `always_keep` (the colour) never."""
    if not 0.0 <= p_drop <= 1.0:
        raise ConfigError(f"{P_DROP_KEY}={p_drop!r}: expected a probability in [0, 1]")
    keep = torch.rand((n, n_features), generator=generator) >= p_drop
    keep[:, list(always_keep)] = True
    return keep


def uniform_size_keep_mask(
    n: int,
    n_features: int,
    generator: torch.Generator | None = None,
    always_keep: Sequence[int] = (),
) -> torch.Tensor:
    """A (n, n_features) bool mask, True = keep: per sample, the number of kept features besides
    `always_keep`, k, is uniform over 0..m (m = n_features minus the always-kept ones), and which k is a
    uniform random subset of that size (the first k of a random permutation: each subset of size k has
    probability 1 / ((m + 1) C(m, k))). The greedy selection scores the probe on every size, so it must
    train on every size (module docstring). The permutation ranks float64 uniforms: a tie, which would
    favour one order, has probability ~m^2 2^-54 per sample."""
    always = torch.zeros(n_features, dtype=torch.bool)
    always[list(always_keep)] = True
    free = (~always).nonzero().flatten()
    m = len(free)
    sizes = torch.randint(0, m + 1, (n, 1), generator=generator)
    ranks = torch.rand((n, m), generator=generator, dtype=torch.float64).argsort(dim=1).argsort(dim=1)
    keep = torch.ones((n, n_features), dtype=torch.bool)
    keep[:, free] = ranks < sizes
    return keep


def keep_mask(
    subsets: str,
    n: int,
    n_features: int,
    p_drop: float,
    generator: torch.Generator | None = None,
    always_keep: Sequence[int] = (),
) -> torch.Tensor:
    """The probe's (n, n_features) keep mask under the scheme `subsets` (`dataset.feature_selection.subsets`):
    `uniform_size` (`uniform_size_keep_mask`; `p_drop` unused) or `independent` (`random_keep_mask`);
    another name: a one-line ConfigError."""
    if subsets == "uniform_size":
        return uniform_size_keep_mask(n, n_features, generator, always_keep)
    if subsets == "independent":
        return random_keep_mask(n, n_features, p_drop, generator, always_keep)
    raise ConfigError(f"{SUBSETS_KEY}={subsets!r}: expected one of {list(SUBSETS)}")


def drop_features(
    inputs: torch.Tensor,
    keep: torch.Tensor,
    slices: Sequence[tuple[str, slice]],
    neutral: torch.Tensor,
    channel_axis: int = 1,
) -> torch.Tensor:
    """A new tensor equal to `inputs` except that the channels of the features not kept are exactly their
    neutral values. `inputs`: (N, C, H, W) (channel_axis 1) or (N, k, C, H, W) (channel_axis 2);
    `keep`: (N, F) bool, one row per sample (dim 0), one column per entry of `slices`; `neutral`: (C,).
    Channels that no slice covers are kept."""
    n_channels = inputs.shape[channel_axis]
    if neutral.shape != (n_channels,):
        raise ValueError(f"neutral has shape {tuple(neutral.shape)}, expected ({n_channels},)")
    if keep.shape != (inputs.shape[0], len(slices)):
        raise ValueError(f"keep has shape {tuple(keep.shape)}, expected ({inputs.shape[0]}, {len(slices)})")
    # Owner feature of each channel; uncovered channels point at an extra always-kept column.
    owner = torch.full((n_channels,), len(slices), dtype=torch.long)
    for i, (_, s) in enumerate(slices):
        owner[s] = i
    keep = torch.cat([keep.bool(), keep.new_ones((keep.shape[0], 1), dtype=torch.bool)], dim=1)
    channel_keep = keep[:, owner.to(keep.device)]  # (N, C)
    tail = inputs.ndim - channel_axis - 1
    mask = channel_keep.reshape(inputs.shape[0], *([1] * (channel_axis - 1)), n_channels, *([1] * tail))
    fill = neutral.to(device=inputs.device, dtype=inputs.dtype).reshape(n_channels, *([1] * tail))
    return torch.where(mask, inputs, fill)


def keep_only(selected: Collection[str], features: Features) -> torch.Tensor:
    """(F,) bool: True for the entries of `features` that are in `selected`; a one-line ConfigError when
    `selected` names a feature that `features` (the probe's inputs) lacks."""
    missing = sorted(set(map(str, selected)) - set(map(str, features)))
    if missing:
        raise ConfigError(
            f"{FEATURE_SELECTION_KEY}: {missing} are not among the probe's features {list(features)}"
        )
    chosen = set(map(str, selected))
    return torch.tensor([str(f) in chosen for f in features], dtype=torch.bool)


def spread_indices(total: int, count: int | None) -> list[int]:
    """`count` indices spread evenly over range(total) (all of them when count is None or >= total): the
    validation batches a subset is scored on. Unshuffled validation data lists one sequence after another,
    so the first `count` batches would see one scene only."""
    if count is None or count >= total:
        return list(range(total))
    return sorted({int(i * total / count) for i in range(count)})


def greedy_forward_selection(
    loss_of: Callable[[Sequence[str]], float],
    candidates: Sequence[str],
    start: Sequence[str],
    max_size: int | None = None,
    progress: bool = True,
) -> list[Row]:
    """Greedy forward selection: row 0 is `start`'s loss (`added` None); each later round adds the
    candidate whose addition gives the lowest `loss_of(selection)` (ties and NaNs: the earlier
    candidate), until `max_size` features are added (None: every candidate). Candidates in `start` are
    skipped. Rows: {"round", "added", "features" (ordered selection so far, start included), "loss"}."""
    remaining = remaining_candidates(candidates, start)
    if max_size is not None and max_size < 0:
        raise ConfigError(f"{FEATURE_SELECTION_KEY}.max_size={max_size!r}: expected >= 0 or null (all)")
    rounds = len(remaining) if max_size is None else min(max_size, len(remaining))
    selected = list(start)
    rows: list[Row] = [
        {"round": 0, "added": None, "features": list(selected), "loss": float(loss_of(selected))}
    ]
    total = sum(len(remaining) - r for r in range(rounds))
    with tqdm(total=total, desc="feature selection", unit="eval", disable=not progress) as bar:
        for r in range(1, rounds + 1):
            best, best_loss = None, None
            for c in remaining:
                loss = float(loss_of([*selected, c]))
                bar.update(1)
                if best is None or loss < best_loss or (math.isnan(best_loss) and not math.isnan(loss)):
                    best, best_loss = c, loss
            selected.append(best)
            remaining.remove(best)
            rows.append({"round": r, "added": best, "features": list(selected), "loss": best_loss})
            bar.set_postfix(added=best, loss=f"{best_loss:.4g}")
    return rows
