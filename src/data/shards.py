"""Preprocessed KPCN data on disk: patch shards, full images, and the `preprocess_dataset` stage.

Layout under `out_dir`:

    splits.json                 {"train": [scenes], "val": [...], "test": [...]}
    whitening.json              per-channel mean/std of diffuse_in / specular_in, TRAIN patches only
    summary.json                what `preprocess_dataset` returns
    patch_sampling.png          importance map, candidate and kept patches of the first train image
    patches/<split>/index.json  (train, val) one shard per (scene, noisy spp)
    patches/<split>/<scene>-<NNNNN>spp.pt
    full/<split>/index.json     (val, test) full images for validation / evaluation
    full/<split>/<scene>-<NNNNN>spp.pt

A shard is a `torch.save`d dict of float32 tensors, channel first: (N, C, P, P) for patches, (C, H, W) for
full images, under `SHARD_KEYS` (plus int64 `corners` (N, 2) for patches). The GP filters' features
(`GP_SHARD_KEYS`: world position, secondary albedo and their variances, unnormalised) are stored only when
the raw files have them (our renders; not real KPCN data nor renders older than these buffers): a dataset
whose files lack them has no such keys in its shards, and its index's `channels` does not list them, so a
filter that needs one reports it missing instead of filtering with zeros. A dataset has them in all its
noisy files or in none (a mix is a one-line error: render again). float32 rather than float16:
the inputs hold HDR radiance and variances spanning many decades, which float16 (max 65504, smallest
normal 6e-5) would clip or flush to zero; shards are small at KPCN patch sizes anyway. Every file is
written atomically; an index is written after all its shards, so an index only lists complete files.
"""

from __future__ import annotations

import json
import os
import zlib
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from src.data.features import CANDIDATE_CHANNELS
from src.data.kpcn_preprocess import (
    GP_FEATURE_KEYS,
    RunningMoments,
    gp_feature_arrays,
    make_network_inputs,
    make_targets,
    save_whitening_stats,
)
from src.data.patch_sampling import (
    check_importance,
    configured_importance_map,
    extract_patches,
    sample_patches,
    save_sampling_figure,
)
from src.data.splits import SPLITS, group_dataset, patch_quota, split_scenes
from src.errors import DataError
from src.io.atomic import atomic_path, atomic_write_json

_RGB = ("r", "g", "b")
#: Tensors in every shard / full image, with their channel names.
SHARD_CHANNELS: dict[str, tuple[str, ...]] = {
    "diffuse_in": CANDIDATE_CHANNELS,  # every candidate feature; a run selects `task.features` at load
    "specular_in": CANDIDATE_CHANNELS,
    "diffuse_target": _RGB,  # reference diffuse / (noisy albedo + eps)
    "specular_target": _RGB,  # log(1 + reference specular)
    "albedo": _RGB,  # noisy albedo, for rebuild_color
    "normal": ("x", "y", "z"),  # noisy shading normal (guide of the cross-bilateral / OIDN baselines)
    "depth": ("z",),  # depth normalised to [0, 1] per image (same as the input channel)
    "color": _RGB,  # noisy colour (baselines, metrics)
    "color_var": ("var",),  # its variance of the pixel mean, linear (the GP filters' colorVariance)
    "reference": _RGB,  # reference colour
    # Optional (`GP_SHARD_KEYS`): the GP filters' features, when the raw files have them.
    "position": ("x", "y", "z"),  # world position of the first hit (0 on escape)
    "position_var": ("var",),  # its variance of the pixel mean (mean over x, y, z)
    "secondary_albedo": _RGB,  # albedo where the mirror-reflected camera ray hits (0 on escape)
    "secondary_albedo_var": ("var",),
}
SHARD_KEYS = tuple(SHARD_CHANNELS)
#: Keys stored only when the raw data have them.
GP_SHARD_KEYS = tuple(GP_FEATURE_KEYS.values())
#: Every stored channel as `<key>.<channel>` (part of the preprocess cache key: a new channel set rebuilds).
SHARD_CHANNEL_NAMES = tuple(f"{k}.{c}" for k, chans in SHARD_CHANNELS.items() for c in chans)
INDEX_NAME = "index.json"
SAMPLING_FIGURE = "patch_sampling.png"


def shard_name(scene: str, spp: int) -> str:
    return f"{scene}-{spp:05d}spp.pt"


def save_tensors(path: str | os.PathLike[str], tensors: Mapping[str, torch.Tensor]) -> None:
    """`torch.save` a dict of tensors atomically."""
    with atomic_path(path) as tmp:
        torch.save(dict(tensors), tmp)


def load_tensors(path: str | os.PathLike[str]) -> dict[str, torch.Tensor]:
    """Load a shard (tensors only: `weights_only=True`, no pickled code)."""
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except (OSError, RuntimeError, EOFError) as e:
        raise DataError(f"{path}: cannot read shard ({e})") from e


def read_index(directory: str | os.PathLike[str]) -> dict[str, Any]:
    path = Path(directory) / INDEX_NAME
    try:
        return json.loads(path.read_text())
    except FileNotFoundError as e:
        raise DataError(f"{path}: no index; run the preprocess stage first") from e
    except ValueError as e:
        raise DataError(f"{path}: malformed index ({e})") from e


def channels_first(a: np.ndarray) -> torch.Tensor:
    """(..., H, W, C) numpy -> (..., C, H, W) contiguous float32 tensor."""
    return torch.from_numpy(np.ascontiguousarray(np.moveaxis(a, -1, -3), dtype=np.float32))


def image_rng(seed: int, scene: str, spp: int) -> np.random.Generator:
    """A generator per image, from the seed and a stable hash of its name: independent of the order
    (and the subset) in which images are processed."""
    return np.random.default_rng([seed, zlib.crc32(scene.encode()), spp])


def _color(buffers: Mapping[str, np.ndarray], path: Path) -> np.ndarray:
    if "color" not in buffers:
        raise DataError(f"{path}: no 'color' buffer (have {sorted(buffers)})")
    return np.asarray(buffers["color"], dtype=np.float32)


def _default_load_fn(path: Path) -> Mapping[str, np.ndarray]:
    from src.data.kpcn_buffers import load_kpcn_exr  # lazy: the EXR loader is an optional dependency here

    return load_kpcn_exr(path)[0]


def _image_arrays(
    noisy: Mapping, ref: Mapping, noisy_path: Path, ref_path: Path, eps: float, specular_variance: str
) -> dict:
    """Everything stored for one noisy image (H, W, C arrays): network inputs, targets, guides, colours."""
    color, ref_color = _color(noisy, noisy_path), _color(ref, ref_path)
    if color.shape != ref_color.shape:
        raise DataError(f"{noisy_path}: {color.shape} vs reference {ref_color.shape}")
    inputs = make_network_inputs(noisy, eps, specular_variance)
    return {
        "diffuse_in": inputs["diffuse_in"],
        "specular_in": inputs["specular_in"],
        **make_targets(ref, inputs["albedo"], eps),
        "albedo": inputs["albedo"],
        "normal": inputs["normal"],
        "depth": inputs["depth"],
        "color": color,
        "color_var": np.asarray(noisy["colorVariance"], dtype=np.float32),
        "reference": ref_color,
        **gp_feature_arrays(noisy, str(noisy_path)),
    }


def _patches(image: dict, noisy: Mapping, rng: np.random.Generator, sampling: Mapping[str, Any], n: int):
    """(`n` patches of every array of `image`, their corners, the candidates, the importance map), sampled
    where the noisy image is hardest to denoise."""
    imp = configured_importance_map(noisy, sampling)
    corners, candidates = sample_patches(
        imp,
        sampling["patch_size"],
        n,
        rng,
        candidates_factor=sampling["candidates_factor"],
        min_keep_prob=sampling["min_keep_prob"],
        min_distance=sampling["min_distance"],
        return_candidates=True,
    )
    patches = {k: extract_patches(v, corners, sampling["patch_size"]) for k, v in image.items()}
    return patches, corners, candidates, imp


def _write_indices(
    out_dir: Path, indices: Mapping[tuple[str, str], list], patch_size: int, keys: tuple[str, ...]
) -> None:
    channels = {k: list(v) for k, v in SHARD_CHANNELS.items() if k in keys}
    for (kind, split), entries in indices.items():
        index = {"kind": kind, "split": split, "dtype": "float32", "channels": channels, "shards": entries}
        if kind == "patches":
            index["patch_size"] = patch_size
        atomic_write_json(out_dir / kind / split / INDEX_NAME, index)


class _ShardWriter:
    """Writes each noisy image's patch shard (train, val) and full image (val, test), collecting the
    index entries and the whitening moments of the train patches; `finish` writes what lists them."""

    def __init__(self, out_dir: Path, sampling: Mapping[str, Any]) -> None:
        self.out_dir, self.sampling = out_dir, sampling
        self.figure_written = False  # SAMPLING_FIGURE: of the first train image
        self.keys: tuple[str, ...] | None = None  # what every image stores: set by the first one
        self.first_file = ""
        self.moments = {"diffuse_in": RunningMoments(), "specular_in": RunningMoments()}
        self.indices: dict[tuple[str, str], list[dict[str, Any]]] = {
            (kind, s): []
            for kind, ss in (("patches", ("train", "val")), ("full", ("val", "test")))
            for s in ss
        }

    def add(self, split: str, entry: dict[str, Any], image: dict, noisy: Mapping, n_patches: int) -> None:
        """Store one noisy image: `n_patches` patches (train, val) and/or the whole image (val, test)."""
        keys = tuple(k for k in SHARD_KEYS if k in image)
        if self.keys is None:
            self.keys, self.first_file = keys, entry["file"]
        elif keys != self.keys:
            has = [k for k in GP_SHARD_KEYS if k in image]
            raise DataError(
                f"{entry['file']}: has the GP features {has or 'none'}, but {self.first_file} has "
                f"{[k for k in GP_SHARD_KEYS if k in self.keys] or 'none'}; a dataset needs them in all its "
                "noisy files or in none (render them again with stage=render)"
            )
        if split in ("train", "val"):
            rng = image_rng(self.sampling["sample_seed"], entry["scene"], entry["spp"])
            patches, corners, candidates, imp = _patches(image, noisy, rng, self.sampling, n_patches)
            if split == "train" and not self.figure_written:
                title = f"{entry['scene']} {entry['spp']} spp: importance ({self.sampling['importance']})"
                save_sampling_figure(
                    self.out_dir / SAMPLING_FIGURE,
                    imp,
                    candidates,
                    corners,
                    self.sampling["patch_size"],
                    title,
                )
                self.figure_written = True
            if split == "train":
                for k, m in self.moments.items():
                    m.update(patches[k])
            shard = {k: channels_first(v) for k, v in patches.items()}
            shard["corners"] = torch.from_numpy(corners)
            save_tensors(self.out_dir / "patches" / split / entry["file"], shard)
            self.indices["patches", split].append({**entry, "n_patches": len(corners)})
        if split in ("val", "test"):
            full = {k: channels_first(v) for k, v in image.items()}
            save_tensors(self.out_dir / "full" / split / entry["file"], full)
            h, w = image["color"].shape[:2]
            self.indices["full", split].append({**entry, "height": h, "width": w})

    def finish(self, raw_dir, splits: Mapping[str, list[str]], n_images: int) -> dict[str, Any]:
        """Indices (after all their shards), whitening statistics, splits and the summary it returns."""
        out_dir, indices = self.out_dir, self.indices
        _write_indices(out_dir, indices, self.sampling["patch_size"], self.keys or SHARD_KEYS)
        stats = {k: m.finalize(self.sampling["whiten_eps"]) for k, m in self.moments.items()}
        save_whitening_stats(out_dir / "whitening.json", stats)
        atomic_write_json(out_dir / "splits.json", splits)
        summary = {
            "raw_dir": str(raw_dir),
            "splits": {s: len(splits[s]) for s in SPLITS},
            "noisy_images": n_images,
            "patches": {s: sum(e["n_patches"] for e in indices["patches", s]) for s in ("train", "val")},
            "full_images": {s: len(indices["full", s]) for s in ("val", "test")},
            "gp_features": [k for k in GP_SHARD_KEYS if k in (self.keys or ())],
            "settings": dict(self.sampling),
        }
        atomic_write_json(out_dir / "summary.json", summary)
        return summary


def _split_quota(
    groups: Mapping[str, Mapping[int, Path]], scenes: list[str], per_image: int, total: int | None
):
    """Patches per noisy image of one split, in processing order: `per_image` each, or `total` spread
    evenly when the split's patch count is fixed (`patches_per_split`)."""
    n_images = sum(len(groups[sc]) - 1 for sc in scenes)
    return [per_image] * n_images if total is None else patch_quota(n_images, total)


def preprocess_dataset(
    raw_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    eps: float,
    patch_size: int,
    patches_per_image: int,
    patches_per_split: Mapping[str, int] | None = None,
    split_fractions: Mapping[str, float],
    split_seed: int,
    sample_seed: int,
    candidates_factor: float,
    min_keep_prob: float,
    min_distance: float | None,
    whiten_eps: float,
    load_fn: Callable[[Path], Mapping[str, np.ndarray]] | None = None,
    split_by_base: bool = False,
    importance: str = "thesis",
    importance_window: float = 1.0,
    importance_percentile: float = 99.0,
    specular_variance: str = "delta",
    progress: bool = True,
) -> dict[str, Any]:
    """Raw `<scene>-<NNNNN>spp.exr` files -> splits, patch shards, full images, whitening stats.

    Scenes are split (by scene) with `split_fractions` / `split_seed` / `split_by_base`. For every scene the
    highest spp is the reference and each lower spp a noisy input: train and val images give
    importance-sampled patch shards (`patches_per_image` each, or `patches_per_split[split]` spread evenly
    over the split), following the `importance` map: `thesis`, the local variance over `importance_window`
    patch sizes, or `mc_variance` (see `patch_sampling.py`); val and test images are also stored whole, for
    full-image validation and evaluation. Whitening statistics come from the train patches only.
    `load_fn` maps a path to a buffer dict (default: `load_kpcn_exr(path)[0]`, imported lazily).
    Deterministic given the seeds. Returns (and writes to summary.json) the counts and settings;
    `patch_sampling.png` shows the sampling of the first train image (the thesis's Figs. 4.4-4.5).
    """
    check_importance(importance)
    settings = {
        "eps": eps,
        "patch_size": patch_size,
        "patches_per_image": patches_per_image,
        "patches_per_split": dict(patches_per_split) if patches_per_split else None,
        "split_fractions": dict(split_fractions),
        "split_seed": split_seed,
        "sample_seed": sample_seed,
        "candidates_factor": candidates_factor,
        "min_keep_prob": min_keep_prob,
        "min_distance": min_distance,
        "whiten_eps": whiten_eps,
        "importance": importance,
        "importance_window": importance_window,
        "importance_percentile": importance_percentile,
        "specular_variance": specular_variance,
    }
    if split_by_base:  # absent when off: the summaries of folders made before the option stay the same
        settings["split_by_base"] = True
    load_fn = load_fn or _default_load_fn
    out_dir = Path(out_dir)
    groups = group_dataset(raw_dir)
    splits = split_scenes(groups, split_fractions, split_seed, split_by_base)
    writer = _ShardWriter(out_dir, settings)
    n_images = sum(len(groups[sc]) - 1 for sc in groups)
    bar = tqdm(total=n_images, desc="preprocess", unit="img", disable=not progress)
    for split in SPLITS:
        quota = iter(
            _split_quota(groups, splits[split], patches_per_image, (patches_per_split or {}).get(split))
        )
        for scene in splits[split]:
            ref_spp = max(groups[scene])
            ref = load_fn(groups[scene][ref_spp])
            for spp in sorted(groups[scene])[:-1]:
                noisy = load_fn(groups[scene][spp])
                paths = (groups[scene][spp], groups[scene][ref_spp])
                image = _image_arrays(noisy, ref, *paths, eps, specular_variance)
                entry = {"file": shard_name(scene, spp), "scene": scene, "spp": spp, "reference_spp": ref_spp}
                writer.add(split, entry, image, noisy, next(quota))
                bar.update(1)
    bar.close()
    return writer.finish(raw_dir, splits, n_images)
