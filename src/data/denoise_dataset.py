"""Torch datasets over what `src.data.shards.preprocess_dataset` wrote.

- `PatchShardDataset`: training/validation patches, streamed one shard at a time (memory is bounded by
  the largest shard, not the dataset), shuffled per epoch, shards divided among DataLoader workers.
- `FullImageDataset`: whole val/test images, one file per (scene, spp), map-style.

Both yield dicts of float32 tensors, channel first, under `SHARD_KEYS`, plus `diffuse_t` / `specular_t`
(the transformed noisy colours, channels 0:3 of the stored inputs: what a KPCN filters and what
`rebuild_color` needs alongside `albedo`). `diffuse_in` / `specular_in` hold only the channels of
`features` (`task.features`, default the paper's 28), selected by name from the stored candidates.

For the filters that read guide features by name (`src.models.filters.gp_filter`), the items also hold
`GUIDE_KEYS` (`visibility`, `normal_var`, `albedo_var`, `depth_var`, `visibility_var`: one channel each,
unwhitened, taken from the stored candidates whatever `features` selects) and, when the prepared data have
them, the GP features `position`, `position_var`, `secondary_albedo`, `secondary_albedo_var`
(`src.data.shards.GP_SHARD_KEYS`); data without them have no such keys.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset, IterableDataset, get_worker_info

from src.data.features import PAPER_FEATURES, Features, channel_indices, feature_channels
from src.data.kpcn_preprocess import WhiteningStats, load_whitening_stats, whiten
from src.data.shards import INDEX_NAME, SHARD_KEYS, load_tensors, read_index

Whitening = Mapping[str, WhiteningStats] | str | os.PathLike[str] | None
#: One-channel guide features exposed under their channel name (module docstring).
GUIDE_KEYS = ("visibility", "normal_var", "albedo_var", "depth_var", "visibility_var")


def guide_selection(index: Mapping[str, Any]) -> dict[str, int]:
    """Positions of `GUIDE_KEYS` among the stored input channels (those the data have)."""
    stored = list(index["channels"]["diffuse_in"])
    return {k: stored.index(k) for k in GUIDE_KEYS if k in stored}


def _prepare(
    data: dict[str, torch.Tensor],
    select: torch.Tensor,
    whitening: Mapping[str, WhiteningStats] | None,
    channel_axis: int,
    guides: Mapping[str, int] | None = None,
):
    """Select SHARD_KEYS (those stored), add the raw transformed colours and the `guides` (key -> stored
    input channel), keep the `select`ed input channels, whiten them if asked (`whitening` already selected
    alike)."""
    out = {k: data[k] for k in SHARD_KEYS if k in data}
    for key, i in (guides or {}).items():
        out[key] = data["diffuse_in"].narrow(channel_axis, i, 1)
    for branch in ("diffuse", "specular"):
        key = f"{branch}_in"
        out[f"{branch}_t"] = out[key].narrow(channel_axis, 0, 3)
        out[key] = out[key].index_select(channel_axis, select)
        if whitening is not None:
            out[key] = whiten(out[key], whitening[key], channel_axis=channel_axis)
    return out


def input_selection(index: Mapping[str, Any], features: Features, where: Path) -> torch.Tensor:
    """Positions of the `features`' channels among the stored inputs an index lists."""
    stored = index["channels"]["diffuse_in"]
    return torch.tensor(channel_indices(feature_channels(features), stored, str(where / INDEX_NAME)))


def selected_whitening(whitening: Whitening, select: torch.Tensor) -> Mapping[str, WhiteningStats] | None:
    """Whitening statistics (a dict, or the path of whitening.json) of the `select`ed channels only."""
    if isinstance(whitening, str | os.PathLike):
        whitening = load_whitening_stats(whitening)
    if whitening is None:
        return None
    return {key: stats.select(select.tolist()) for key, stats in whitening.items()}


def worker_shard_order(n_shards: int, seed: int, epoch: int, shuffle: bool) -> np.ndarray:
    """The shards this DataLoader worker streams, in order: all shards, shuffled per (seed, epoch) when
    `shuffle`, then dealt round-robin to the workers (each shard read by exactly one worker)."""
    order = np.random.default_rng([seed, epoch]).permutation(n_shards) if shuffle else np.arange(n_shards)
    info = get_worker_info()
    return order if info is None else order[info.id :: info.num_workers]


class ShardStream(IterableDataset):
    """The rows of one split's shards, streamed one shard at a time (memory bounded by the largest shard).

    Each epoch: the shard order is permuted with a generator seeded by (seed, epoch); worker k of n
    takes shards k, k + n, ... of that order (all workers compute the same permutation,
    `worker_shard_order`), and the rows of each shard are permuted with (seed, epoch, shard). So every row
    comes exactly once per epoch, whatever the number of workers. Call `set_epoch` before iterating a
    DataLoader each epoch (with `persistent_workers=False`, the default, workers get a fresh copy of the
    dataset per epoch). The split's shards are listed in `<prepared>/patches/<split>/index.json`, each
    entry with its row count under `rows_key`; a subclass loads one shard's tensors, rows first, with
    `color` among them (`_load_shard`): the still images' patches and the sequences' samples stream alike.
    """

    rows_key: str

    def __init__(self, prepared: str | os.PathLike[str], split: str, seed: int, shuffle: bool) -> None:
        super().__init__()
        self.root = Path(prepared) / "patches" / split
        self.index = read_index(self.root)
        self.shards = self.index["shards"]
        self.patch_size = self.index["patch_size"]
        self.seed, self.shuffle, self.epoch = seed, shuffle, 0

    def __len__(self) -> int:
        return sum(s[self.rows_key] for s in self.shards)

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _my_shards(self) -> np.ndarray:
        return worker_shard_order(len(self.shards), self.seed, self.epoch, self.shuffle)

    def _load_shard(self, i: int) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        for i in self._my_shards():
            data = self._load_shard(i)
            n = data["color"].shape[0]
            rng = np.random.default_rng([self.seed, self.epoch, int(i)])
            for j in rng.permutation(n) if self.shuffle else range(n):
                yield {k: v[j] for k, v in data.items()}
            del data


class PatchShardDataset(ShardStream):
    """Patches of one split from `<shard_dir>/patches/<split>/` (`shard_dir` = preprocess output dir),
    streamed and shuffled per epoch as `ShardStream` says. `whitening`: stats dict or path to
    whitening.json (of all stored channels), applied to the selected diffuse_in / specular_in.
    """

    rows_key = "n_patches"

    def __init__(
        self,
        shard_dir: str | os.PathLike[str],
        split: str,
        *,
        seed: int = 0,
        shuffle: bool = True,
        whitening: Whitening = None,
        features: Features = PAPER_FEATURES,
    ) -> None:
        super().__init__(shard_dir, split, seed, shuffle)
        self.select = input_selection(self.index, features, self.root)
        self.whitening = selected_whitening(whitening, self.select)
        self.guides = guide_selection(self.index)

    def _load_shard(self, i: int) -> dict[str, torch.Tensor]:
        return _prepare(
            load_tensors(self.root / self.shards[i]["file"]),
            self.select,
            self.whitening,
            channel_axis=1,
            guides=self.guides,
        )


class FullImageDataset(Dataset):
    """Full images of one split from `<shard_dir>/full/<split>/` (val, test), one file per item.

    Items are dicts of (C, H, W) tensors plus `scene` (str), `spp` and `reference_spp` (int).
    """

    def __init__(
        self,
        shard_dir: str | os.PathLike[str],
        split: str,
        *,
        whitening: Whitening = None,
        features: Features = PAPER_FEATURES,
    ) -> None:
        self.root = Path(shard_dir) / "full" / split
        self.index = read_index(self.root)
        self.images = self.index["shards"]
        self.select = input_selection(self.index, features, self.root)
        self.whitening = selected_whitening(whitening, self.select)
        self.guides = guide_selection(self.index)

    def __len__(self) -> int:
        return len(self.images)

    @property
    def batch_keys(self) -> frozenset[str]:
        """The tensor keys of every item, from the index (no image read): what `_prepare` returns."""
        stored = [k for k in SHARD_KEYS if k in self.index["channels"]]
        return frozenset((*stored, *self.guides, "diffuse_t", "specular_t"))

    def __getitem__(self, i: int) -> dict[str, Any]:
        meta = self.images[i]
        data = _prepare(
            load_tensors(self.root / meta["file"]),
            self.select,
            self.whitening,
            channel_axis=0,
            guides=self.guides,
        )
        return {**data, "scene": meta["scene"], "spp": meta["spp"], "reference_spp": meta["reference_spp"]}


class FramesOfOne(IterableDataset):
    """Patches as samples of one frame: the batch contract's frame axis (k = 1, `src.models.denoise.base`)
    put in front of every tensor, so still images train like sequences."""

    def __init__(self, patches: PatchShardDataset) -> None:
        super().__init__()
        self.patches = patches

    def set_epoch(self, epoch: int) -> None:
        self.patches.set_epoch(epoch)

    def __len__(self) -> int:
        return len(self.patches)

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        for item in self.patches:
            yield {k: v[None] for k, v in item.items()}


class ImagesAsFrames(Dataset):
    """Full images as sequences of one frame (the frame axis put in front of every tensor; `scene`,
    `spp` and `reference_spp` as they are)."""

    def __init__(self, images: FullImageDataset) -> None:
        self.images = images

    def __len__(self) -> int:
        return len(self.images)

    def __getitem__(self, i: int) -> dict[str, Any]:
        return {k: v[None] if isinstance(v, torch.Tensor) else v for k, v in self.images[i].items()}
