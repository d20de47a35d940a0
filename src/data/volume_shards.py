"""Preprocessed volumetric sequences (`stage=preprocess dataset=volumetric`, issue 16): training samples
of k consecutive frames of one crop, and whole sequences for evaluation.

From the rendered `<scene>-f<FFFF>-<NNNNN>spp.exr` files (`src.data.volume_buffers`): scenes are split
by scene (`splits.split_scenes`); in every scene the highest sample count is the reference and every
lower one a noisy *sequence* of the scene's F frames. For each noisy sequence, per frame:

* `inputs`: every candidate input channel (`VOLUME_CANDIDATE_CHANNELS`, 62: each buffer's value and its
  variance, transformed as `src.data.volume_features` says; radiance under `volume_transform`), from
  which a run selects `dataset.volume_features` by name at load time;
* `target`, `target_surface`, `target_volume`: the reference's colour, surface and volume radiance under
  the same `volume_transform` (`inverse_volume_transform` gives back the linear reference);
* `color`, `reference`: the noisy and the reference colour, linear (baselines, metrics);
* `reference2` (`second_reference`, whole val/test sequences only): the colour of the second, independently
  seeded reference `<raw>/reference2/<scene>-f<FFFF>-<NNNNN>spp.exr` (`src.render.volume_dataset`), linear,
  from which evaluation estimates the flicker against the noise-free truth
  (`src.metrics.temporal.flicker_unbiased`). Never in training samples (nothing trains on it), never in
  data rendered without it (then the full indices do not name it and evaluation leaves that metric out).

A training sample (train and val splits) is the same crop over `sequence_frames` = k consecutive frames,
sampled by `sequence_patches.sample_sequence_patches` on per-frame importance maps (the thesis map of
the noisy colour and normals by default). Layout under `out_dir`, as `src.data.shards`:

    splits.json                 {"train": [scenes], "val": [...], "test": [...]}
    whitening.json              per-channel mean/std of `inputs`, TRAIN samples only
    summary.json                what `preprocess_volume_dataset` returns
    patches/<split>/index.json  (train, val) one shard per (scene, noisy spp)
    patches/<split>/<scene>-<NNNNN>spp.pt   (n, k, C, P, P) tensors; int64 `starts` (n,), `corners` (n, 2)
    full/<split>/index.json     (val, test) one whole sequence per (scene, noisy spp); its channels name
                                `reference2` when the sequences hold it
    full/<split>/<scene>-<NNNNN>spp.pt      (F, C, H, W) tensors

float32 throughout (HDR radiance and variances, as `shards.py` argues). Every file is written
atomically and an index after all its shards, so an index only lists complete files; the indices name
every tensor's channels. A whole noisy sequence and the reference's colour, surface and volume are in
memory at once (at the paper profile's 16 frames of 1280x720, about 6 GB).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from src.data.kpcn_preprocess import RunningMoments, save_whitening_stats
from src.data.patch_sampling import check_importance, configured_importance_map
from src.data.sequence_patches import FRAMES_KEY, extract_sequence_patches, sample_sequence_patches
from src.data.shards import channels_first, image_rng, save_tensors, shard_name
from src.data.splits import SPLITS, split_scenes
from src.data.transforms import check_volume_transform, log_modulus, log_modulus_variance, volume_transform
from src.data.volume_buffers import SECOND_REFERENCE_DIR, group_volume_dataset, volume_exr_name
from src.data.volume_features import (
    NO_VARIANCE,
    VALUE_KINDS,
    VOLUME_CANDIDATE_CHANNELS,
    VOLUME_FEATURE_BUFFERS,
)
from src.errors import ConfigError, DataError
from src.io.atomic import atomic_write_json

_RGB = ("r", "g", "b")
#: Tensors of every sample / sequence, with their channel names.
SEQUENCE_CHANNELS: dict[str, tuple[str, ...]] = {
    "inputs": VOLUME_CANDIDATE_CHANNELS,  # every candidate; a run selects `dataset.volume_features` at load
    "target": _RGB,  # reference colour, under volume_transform
    "target_surface": _RGB,  # reference surface radiance, under volume_transform
    "target_volume": _RGB,  # reference volume radiance, under volume_transform
    "color": _RGB,  # noisy colour, linear
    "reference": _RGB,  # reference colour, linear
}
SEQUENCE_KEYS = tuple(SEQUENCE_CHANNELS)
#: The second reference's colour, linear: stored in the whole held-out sequences of data rendered with
#: `dataset.second_reference` only (not one of `SEQUENCE_KEYS`, which every item holds).
SECOND_REFERENCE_KEY = "reference2"
#: The splits whose whole sequences are stored (and evaluated, `task.eval.split`): they get the second
#: reference.
FULL_SPLITS = ("val", "test")
#: The buffers read from a noisy file: every feature buffer and its variance (not the world points).
NOISY_BUFFERS = tuple(VOLUME_FEATURE_BUFFERS) + tuple(
    f"{b}Variance" for b in VOLUME_FEATURE_BUFFERS if b not in NO_VARIANCE
)
#: The buffers read from a reference file.
REFERENCE_BUFFERS = ("color", "surface", "volume")
_DISTANCES = tuple(b for b, kind in VALUE_KINDS.items() if kind == "distance")

LoadFn = Callable[[Path, Sequence[str]], Mapping[str, np.ndarray]]


def transform_pair(
    kind: str, value: np.ndarray, var: np.ndarray | None, transform: str, distance_scale: float
) -> tuple[np.ndarray, np.ndarray | None]:
    """One buffer's stored value and variance, (..., C) and (..., 1), by its `VALUE_KINDS` kind:
    radiance / unbounded: `volume_transform` with the first-order variance Var / (1 + mean_c |x|)^2
    (`log_modulus_variance`); distance: both divided by `distance_scale` (variance by its square; a
    scale of 0, nothing hit in the whole sequence, leaves zeros); as_is: unchanged."""
    if kind in ("radiance", "unbounded"):
        if transform == "log_modulus":
            return log_modulus(value), None if var is None else log_modulus_variance(var, value)
        return value, var
    if kind == "distance":
        if distance_scale <= 0.0:
            return np.zeros_like(value), None if var is None else np.zeros_like(var)
        return value / distance_scale, None if var is None else var / distance_scale**2
    if kind == "as_is":
        return value, var
    raise ValueError(f"unknown value kind {kind!r}")


def _stack(frames: Sequence[Mapping[str, np.ndarray]], names: Iterable[str], what: str) -> dict:
    """{buffer: (F, H, W, C) float32} of the frames' buffers `names`."""
    out = {}
    for name in names:
        try:
            out[name] = np.stack([np.asarray(f[name], dtype=np.float32) for f in frames])
        except KeyError as e:
            raise DataError(f"{what}: buffer {name!r} is missing") from e
        except ValueError as e:
            raise DataError(f"{what}: buffer {name!r} differs in size between frames ({e})") from e
    return out


def sequence_arrays(
    noisy: Sequence[Mapping[str, np.ndarray]],
    reference: Sequence[Mapping[str, np.ndarray]],
    transform: str,
    what: str = "sequence",
) -> dict[str, np.ndarray]:
    """Everything stored for one noisy sequence (per-frame buffer dicts of the noisy and the reference
    frames, in order): {`SEQUENCE_KEYS` tensor: (F, H, W, C) float32}, channels as `SEQUENCE_CHANNELS`.
    Vectorised over frames."""
    check_volume_transform(transform)
    if len(noisy) != len(reference):
        raise DataError(f"{what}: {len(noisy)} noisy frames, {len(reference)} reference frames")
    b = _stack(noisy, NOISY_BUFFERS, what)
    ref = _stack(reference, REFERENCE_BUFFERS, f"{what} reference")
    if ref["color"].shape != b["color"].shape:
        raise DataError(f"{what}: frames of {b['color'].shape[1:3]}, reference {ref['color'].shape[1:3]}")
    scale = max(float(b[d].max()) for d in _DISTANCES)  # one scale per sequence for all distances
    parts = []
    for buffer in VOLUME_FEATURE_BUFFERS:
        var = None if buffer in NO_VARIANCE else b[f"{buffer}Variance"]
        value, var = transform_pair(VALUE_KINDS[buffer], b[buffer], var, transform, scale)
        parts += [value] if var is None else [value, var]
    out = {
        "inputs": np.concatenate(parts, axis=-1),
        **{
            key: volume_transform(ref[buffer], transform)
            for key, buffer in (
                ("target", "color"),
                ("target_surface", "surface"),
                ("target_volume", "volume"),
            )
        },
        "color": b["color"],
        "reference": ref["color"],
    }
    return {k: np.asarray(v, dtype=np.float32) for k, v in out.items()}


def _default_load_fn(path: Path, buffers: Sequence[str]) -> Mapping[str, np.ndarray]:
    from src.data.volume_buffers import load_volume_exr  # lazy: the EXR reader is an optional dependency

    return load_volume_exr(path, buffers=buffers)[0]


class _SequenceWriter:
    """Writes each noisy sequence's sample shard (train, val) and whole sequence (val, test), collecting
    the index entries and the train samples' whitening moments; `finish` writes what lists them."""

    def __init__(self, out_dir: Path, settings: Mapping[str, Any]) -> None:
        self.out_dir, self.settings = out_dir, settings
        self.moments = RunningMoments()
        self.indices: dict[tuple[str, str], list[dict[str, Any]]] = {
            (kind, s): [] for kind, ss in (("patches", ("train", "val")), ("full", FULL_SPLITS)) for s in ss
        }

    def add(self, split: str, entry: dict[str, Any], arrays: dict, importance: np.ndarray) -> None:
        s = self.settings
        if split in ("train", "val"):
            p, k = s["patch_size"], s["sequence_frames"]
            starts, corners = sample_sequence_patches(
                importance,
                p,
                s["patches_per_sequence"],
                k,
                image_rng(s["sample_seed"], entry["scene"], entry["spp"]),
                candidates_factor=s["candidates_factor"],
                min_keep_prob=s["min_keep_prob"],
                min_distance=s["min_distance"],
            )
            samples = {
                key: extract_sequence_patches(arrays[key], starts, corners, p, k) for key in SEQUENCE_KEYS
            }
            if split == "train":
                self.moments.update(samples["inputs"])
            shard = {key: channels_first(v) for key, v in samples.items()}
            shard |= {"starts": torch.from_numpy(starts), "corners": torch.from_numpy(corners)}
            save_tensors(self.out_dir / "patches" / split / entry["file"], shard)
            self.indices["patches", split].append({**entry, "n_samples": len(starts)})
        if split in FULL_SPLITS:
            full = {key: channels_first(v) for key, v in arrays.items()}
            save_tensors(self.out_dir / "full" / split / entry["file"], full)
            h, w = arrays["color"].shape[1:3]
            self.indices["full", split].append({**entry, "height": h, "width": w})

    def finish(
        self, raw_dir, splits: Mapping[str, list[str]], n_sequences: int, seconds: float
    ) -> dict[str, Any]:
        channels = {k: list(v) for k, v in SEQUENCE_CHANNELS.items()}
        s = self.settings
        second = {SECOND_REFERENCE_KEY: list(_RGB)} if s.get("second_reference") else {}
        for (kind, split), entries in self.indices.items():
            index = {
                "kind": kind,
                "split": split,
                "dtype": "float32",
                "layout": "(n, k, C, P, P)" if kind == "patches" else "(F, C, H, W)",
                "volume_transform": s["volume_transform"],
                "channels": channels | (second if kind == "full" else {}),
                "shards": entries,
            }
            if kind == "patches":
                index |= {"patch_size": s["patch_size"], "sequence_frames": s["sequence_frames"]}
            atomic_write_json(self.out_dir / kind / split / "index.json", index)
        if self.moments.mean is not None:
            save_whitening_stats(
                self.out_dir / "whitening.json", {"inputs": self.moments.finalize(s["whiten_eps"])}
            )
        atomic_write_json(self.out_dir / "splits.json", splits)
        summary = {
            "raw_dir": str(raw_dir),
            "splits": {sp: len(splits[sp]) for sp in SPLITS},
            "noisy_sequences": n_sequences,
            "samples": {
                sp: sum(e["n_samples"] for e in self.indices["patches", sp]) for sp in ("train", "val")
            },
            "full_sequences": {sp: len(self.indices["full", sp]) for sp in ("val", "test")},
            "input_channels": len(VOLUME_CANDIDATE_CHANNELS),
            "seconds": round(seconds, 3),
            "settings": dict(s),
        }
        atomic_write_json(self.out_dir / "summary.json", summary)
        return summary


def second_reference_paths(raw_dir, scene: str, frames: Mapping) -> list[Path]:
    """The files of the second reference of `scene`, `<raw_dir>/reference2/<scene>-f<FFFF>-<ref spp>spp.exr`
    for every frame at the reference's sample count; a one-line DataError when one is missing (a render of
    another split or without `dataset.second_reference`)."""
    ref_spp = max(frames[0])
    paths = [Path(raw_dir) / SECOND_REFERENCE_DIR / volume_exr_name(scene, f, ref_spp) for f in frames]
    missing = [p for p in paths if not p.is_file()]
    if missing:
        raise DataError(
            f"{missing[0]}: the second reference of held-out scene {scene!r} (dataset.second_reference=true) "
            f"is missing ({len(missing)} of its {len(paths)} frames); run stage=render with the same "
            "task.preprocess.split, split_seed and split_by_base as stage=preprocess"
        )
    return paths


def second_reference_colour(raw_dir, scene: str, frames: Mapping, load_fn: LoadFn) -> np.ndarray:
    """(F, H, W, 3) float32: the linear colour of the second reference of `scene`
    (`second_reference_paths`)."""
    paths = second_reference_paths(raw_dir, scene, frames)
    colour = _stack(
        [load_fn(p, ("color",)) for p in paths], ("color",), f"{raw_dir}: {scene} second reference"
    )
    return colour["color"]


def _scene_sequences(
    raw_dir,
    scene: str,
    frames: Mapping,
    load_fn: LoadFn,
    settings: Mapping[str, Any],
    second_reference: bool = False,
):
    """(index entry, stored arrays, per-frame importance maps) of each noisy sequence of one scene; the
    reference is the scene's highest sample count. `second_reference`: the arrays also hold `reference2`
    (`second_reference_colour`), the same for every noisy sequence of the scene."""
    counts = sorted(frames[0])
    ref_spp = counts[-1]
    ref = [load_fn(frames[f][ref_spp], REFERENCE_BUFFERS) for f in frames]
    ref2 = second_reference_colour(raw_dir, scene, frames, load_fn) if second_reference else None
    for spp in counts[:-1]:
        noisy = [load_fn(frames[f][spp], NOISY_BUFFERS) for f in frames]
        arrays = sequence_arrays(noisy, ref, settings["volume_transform"], f"{raw_dir}: {scene} {spp} spp")
        if ref2 is not None:
            if ref2.shape != arrays["reference"].shape:
                raise DataError(
                    f"{raw_dir}: {scene}: second reference of {ref2.shape[1:3]} per frame, reference "
                    f"{arrays['reference'].shape[1:3]}"
                )
            arrays[SECOND_REFERENCE_KEY] = ref2
        imp = np.stack([configured_importance_map(n, settings) for n in noisy])
        entry = {
            "file": shard_name(scene, spp),
            "scene": scene,
            "spp": spp,
            "reference_spp": ref_spp,
            "frames": len(frames),
        }
        yield entry, arrays, imp


def preprocess_volume_dataset(
    raw_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    patch_size: int,
    patches_per_sequence: int,
    sequence_frames: int,
    split_fractions: Mapping[str, float],
    split_seed: int,
    sample_seed: int,
    volume_transform: str = "log_modulus",
    candidates_factor: float = 4.0,
    min_keep_prob: float = 0.1,
    min_distance: float | None = None,
    importance: str = "thesis",
    importance_window: float = 1.0,
    importance_percentile: float = 99.0,
    whiten_eps: float = 1e-6,
    load_fn: LoadFn | None = None,
    progress: bool = True,
    split_by_base: bool = False,
    second_reference: bool = False,
) -> dict[str, Any]:
    """Rendered volumetric sequences -> splits, sequence-sample shards, whole sequences, whitening stats
    (module docstring). `patches_per_sequence` samples of `sequence_frames` frames of `patch_size`^2 per
    noisy train/val sequence; `candidates_factor`, `min_keep_prob`, `min_distance` (pixels, an upper
    bound; None: half a patch) as in `sample_sequence_patches`. `load_fn(path, buffers)` maps a file to
    its buffer dict (default: `load_volume_exr`). Deterministic given the seeds (one generator per
    sequence, from the seed, the scene and the spp). Returns (and writes to summary.json) the counts and
    the settings. `second_reference` (`dataset.second_reference`): the whole val and test sequences also
    hold `reference2` (`second_reference_colour`; a one-line DataError when a held-out scene lacks it)."""
    check_volume_transform(volume_transform)
    check_importance(importance)
    settings = {
        "patch_size": patch_size,
        "patches_per_sequence": patches_per_sequence,
        "sequence_frames": sequence_frames,
        "split_fractions": dict(split_fractions),
        "split_seed": split_seed,
        "sample_seed": sample_seed,
        "volume_transform": volume_transform,
        "candidates_factor": candidates_factor,
        "min_keep_prob": min_keep_prob,
        "min_distance": min_distance,
        "importance": importance,
        "importance_window": importance_window,
        "importance_percentile": importance_percentile,
        "whiten_eps": whiten_eps,
    }
    if split_by_base:  # absent when off: the summaries of folders made before the option stay the same
        settings["split_by_base"] = True
    if second_reference:  # likewise
        settings["second_reference"] = True
    load_fn = load_fn or _default_load_fn
    out_dir = Path(out_dir)
    start = time.perf_counter()
    groups = group_volume_dataset(raw_dir)
    short = {sc: len(fr) for sc, fr in groups.items() if len(fr) < sequence_frames}
    if short:
        scene, n = next(iter(short.items()))
        raise ConfigError(
            f"{FRAMES_KEY}={sequence_frames} is more than the {n} frame(s) of scene {scene!r} in {raw_dir}"
        )
    splits = split_scenes(groups, split_fractions, split_seed, split_by_base)
    if second_reference:  # every held-out scene's files, before any work
        for scene in (s for split in FULL_SPLITS for s in splits[split]):
            second_reference_paths(raw_dir, scene, groups[scene])
    writer = _SequenceWriter(out_dir, settings)
    n_sequences = sum(len(next(iter(fr.values()))) - 1 for fr in groups.values())
    bar = tqdm(total=n_sequences, desc="preprocess volumetric", unit="seq", disable=not progress)
    for split in SPLITS:
        second = second_reference and split in FULL_SPLITS  # only the whole sequences hold it
        for scene in splits[split]:
            for entry, arrays, imp in _scene_sequences(
                raw_dir, scene, groups[scene], load_fn, settings, second
            ):
                writer.add(split, entry, arrays, imp)
                bar.update(1)
    bar.close()
    return writer.finish(raw_dir, splits, n_sequences, time.perf_counter() - start)
