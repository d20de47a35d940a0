"""Torch datasets over what `src.data.volume_shards.preprocess_volume_dataset` wrote (issue 16).

- `SequencePatchDataset`: training/validation samples, each the same crop over k consecutive frames,
  streamed one shard at a time and shuffled per epoch as `PatchShardDataset` (every sample once per
  epoch, shards divided among DataLoader workers).
- `SequenceDataset`: whole val/test sequences, one per (scene, noisy spp), map-style.

Items are dicts of float32 tensors, frames first then channels: (k, C, P, P) for samples, (F, C, H, W)
for sequences, in the batch contract of `src.models.denoise.base`: the sequences have one branch,
`radiance` (`RADIANCE_BRANCH`), whose input group `radiance_in` holds only the channels of `features`
(`dataset.volume_features`; None: all 62 candidates), selected by name; `radiance_t` is the transformed noisy
colour (what a KPCN's kernels filter) and `radiance_target` the transformed reference. Besides:
`surface_t` / `volume_t` / `target_surface` / `target_volume` (the colour's parts), `color` and
`reference` (linear), and the guides `albedo`, `normal`, `depth` and `motion` (flow in pixels to the next
frame), taken from the stored candidates whatever the selection. Whole sequences of data rendered with
`dataset.second_reference` also hold `reference2` (the second, independently seeded reference, linear),
from which the evaluation scores the flicker against the truth; others do not (never made up).
`inverse_volume_transform(x, dataset.volume_transform)` maps `radiance_target` / `radiance_t` / a
network's output back to linear radiance.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import torch
from torch.utils.data import Dataset

from src.data.denoise_dataset import ShardStream
from src.data.kpcn_preprocess import WhiteningStats, load_whitening_stats, whiten
from src.data.shards import INDEX_NAME, load_tensors, read_index
from src.data.volume_features import Features, volume_channel_indices, volume_feature_channels
from src.data.volume_shards import SECOND_REFERENCE_KEY, SEQUENCE_KEYS

Whitening = Mapping[str, WhiteningStats] | str | os.PathLike[str] | None
#: The one branch of the sequences (`src.models.denoise.base`: its groups `radiance_in`, `radiance_t`,
#: `radiance_target`).
RADIANCE_BRANCH = "radiance"
#: Stored tensors under their batch-contract names (the others keep theirs).
_BATCH_NAMES = {"inputs": f"{RADIANCE_BRANCH}_in", "target": f"{RADIANCE_BRANCH}_target"}
#: Tensors taken from the stored candidates whatever `features` selects: what kernels filter, what filters
#: are guided by, the flow.
_ALWAYS = {
    f"{RADIANCE_BRANCH}_t": ("color_r", "color_g", "color_b"),
    **{f"{b}_t": (f"{b}_r", f"{b}_g", f"{b}_b") for b in ("surface", "volume")},
    "albedo": ("albedo_r", "albedo_g", "albedo_b"),
    "normal": ("normal_x", "normal_y", "normal_z"),
    "depth": ("depth",),
    "motion": ("motion_x", "motion_y"),
}


class _Selection:
    """The stored `inputs` channels a run reads (`features`) and the always-present extras, as index
    tensors into the stored channels; the whitening statistics of the selected ones."""

    def __init__(self, index: Mapping[str, Any], features: Features | None, whitening: Whitening, root: Path):
        stored = index["channels"]["inputs"]
        where = str(root / INDEX_NAME)
        self.inputs = torch.tensor(volume_channel_indices(volume_feature_channels(features), stored, where))
        self.extra = {k: torch.tensor(volume_channel_indices(v, stored, where)) for k, v in _ALWAYS.items()}
        if isinstance(whitening, str | os.PathLike):
            whitening = load_whitening_stats(whitening)
        self.whitening = None if whitening is None else whitening["inputs"].select(self.inputs.tolist())

    def apply(self, data: Mapping[str, torch.Tensor], channel_axis: int) -> dict[str, torch.Tensor]:
        out = {_BATCH_NAMES.get(k, k): data[k] for k in SEQUENCE_KEYS}
        if SECOND_REFERENCE_KEY in data:  # only whole held-out sequences of data rendered with one
            out[SECOND_REFERENCE_KEY] = data[SECOND_REFERENCE_KEY]
        for key, idx in self.extra.items():
            out[key] = data["inputs"].index_select(channel_axis, idx)
        inputs = data["inputs"].index_select(channel_axis, self.inputs)
        if self.whitening is not None:
            inputs = whiten(inputs, self.whitening, channel_axis=channel_axis)
        out[f"{RADIANCE_BRANCH}_in"] = inputs
        return out


class SequencePatchDataset(ShardStream):
    """Samples of one split from `<prepared>/patches/<split>/` (train, val): dicts of (k, C, P, P)
    tensors plus `start` (the first frame) and `corner` (row, col), int64.

    Streamed and shuffled per epoch as `ShardStream` says (every sample exactly once per epoch, whatever
    the number of workers; call `set_epoch` before each epoch). `whitening`: the stats dict or the path
    of whitening.json (of all stored channels), applied to the selected `inputs`.
    """

    rows_key = "n_samples"

    def __init__(
        self,
        prepared: str | os.PathLike[str],
        split: str,
        *,
        features: Features | None = None,
        seed: int = 0,
        shuffle: bool = True,
        whitening: Whitening = None,
    ) -> None:
        super().__init__(prepared, split, seed, shuffle)
        self.frames = self.index["sequence_frames"]
        self.volume_transform = self.index["volume_transform"]
        self.selection = _Selection(self.index, features, whitening, self.root)

    def _load_shard(self, i: int) -> dict[str, torch.Tensor]:
        raw = load_tensors(self.root / self.shards[i]["file"])
        data = self.selection.apply(raw, channel_axis=2)
        return data | {"start": raw["starts"], "corner": raw["corners"]}


class SequenceDataset(Dataset):
    """Whole sequences of one split from `<prepared>/full/<split>/` (val, test), one file per item:
    dicts of (F, C, H, W) tensors (`reference2` too where the index names it) plus `scene` (str), `spp`
    and `reference_spp` (int)."""

    def __init__(
        self,
        prepared: str | os.PathLike[str],
        split: str,
        *,
        features: Features | None = None,
        whitening: Whitening = None,
    ) -> None:
        self.root = Path(prepared) / "full" / split
        self.index = read_index(self.root)
        self.sequences = self.index["shards"]
        self.volume_transform = self.index["volume_transform"]
        self.selection = _Selection(self.index, features, whitening, self.root)

    def __len__(self) -> int:
        return len(self.sequences)

    @property
    def batch_keys(self) -> frozenset[str]:
        """The tensor keys of every item (no sequence read): what `_Selection.apply` returns."""
        second = (SECOND_REFERENCE_KEY,) if SECOND_REFERENCE_KEY in self.index["channels"] else ()
        return frozenset((*(_BATCH_NAMES.get(k, k) for k in SEQUENCE_KEYS), *_ALWAYS, *second))

    def __getitem__(self, i: int) -> dict[str, Any]:
        meta = self.sequences[i]
        data = self.selection.apply(load_tensors(self.root / meta["file"]), channel_axis=1)
        return {**data, "scene": meta["scene"], "spp": meta["spp"], "reference_spp": meta["reference_spp"]}
