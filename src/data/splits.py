"""Dataset file naming and train/val/test splits by SCENE.

Splitting patches (or images of one scene at several sample counts) across splits leaks: validation
would measure memorisation of the same geometry and textures. So every image of a scene lands in one split.
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable, Mapping
from pathlib import Path

import numpy as np

from src.errors import ConfigError, DataError

SPLITS = ("train", "val", "test")

_EXR_NAME = re.compile(r"^(?P<scene>.+)-(?P<spp>\d+)spp\.exr$")


def exr_name(scene: str, spp: int) -> str:
    """The file name of one render: `<scene>-<NNNNN>spp.exr` (the inverse of `parse_exr_name`)."""
    return f"{scene}-{spp:05d}spp.exr"


def parse_exr_name(path: str | os.PathLike[str]) -> tuple[str, int]:
    """`<scene>-<NNNNN>spp.exr` -> (scene, spp); the scene may contain dashes (the last one splits)."""
    name = Path(path).name
    m = _EXR_NAME.match(name)
    if m is None or int(m["spp"]) < 1:
        raise DataError(f"{path}: expected a file name like '<scene>-00016spp.exr'")
    return m["scene"], int(m["spp"])


def group_dataset(raw_dir: str | os.PathLike[str]) -> dict[str, dict[int, Path]]:
    """{scene: {spp: path}} for every `*.exr` in `raw_dir` (sorted by scene, then spp).

    Each scene needs at least two sample counts: noisy inputs plus a reference (its highest spp).
    """
    raw_dir = Path(raw_dir)
    if not raw_dir.is_dir():
        raise DataError(f"{raw_dir}: raw data directory does not exist")
    groups: dict[str, dict[int, Path]] = {}
    for path in sorted(raw_dir.glob("*.exr")):
        scene, spp = parse_exr_name(path)
        groups.setdefault(scene, {})[spp] = path
    if not groups:
        raise DataError(f"{raw_dir}: no '<scene>-<NNNNN>spp.exr' files found")
    single = sorted(s for s, g in groups.items() if len(g) < 2)
    if single:
        raise DataError(
            f"{raw_dir}: scene(s) {single} have a single sample count; each needs noisy image(s) "
            "and a higher-spp reference"
        )
    return {s: dict(sorted(groups[s].items())) for s in sorted(groups)}


#: Where the split fractions come from in the config (their errors name this key).
SPLIT_KEY = "task.preprocess.split"


def base_scene(scene: str) -> str:
    """The base scene of a procedural scene name `<base>-<NNNN>` (`cornell-0003` -> `cornell`); a name
    without such a suffix (a user scene file) is its own base."""
    base, _, index = scene.rpartition("-")
    return base if base and index.isdigit() else scene


def _interleave_bases(order: list[str]) -> list[str]:
    """`order` regrouped round-robin over the base scenes: the first scene of each base (bases in order of
    first appearance), then the second of each, ...; within a base the order is kept."""
    by_base: dict[str, list[str]] = {}
    for name in order:
        by_base.setdefault(base_scene(name), []).append(name)
    rounds = max(len(v) for v in by_base.values())
    return [names[r] for r in range(rounds) for names in by_base.values() if r < len(names)]


def split_scenes(
    scene_names: Iterable[str], fractions: Mapping[str, float], seed: int, by_base: bool = False
) -> dict[str, list[str]]:
    """Partition scenes into train/val/test with the given fractions (normalised to sum 1).

    Deterministic: the names are sorted, then shuffled by a seeded generator. Counts are rounded, with
    at least one scene per split (so >= 3 scenes are needed); train gets the remainder. Each list is
    returned sorted. `by_base` (`task.preprocess.split_by_base`) deals the shuffled scenes round-robin
    over their base scenes before val and test take theirs, so a held-out split of k scenes holds
    min(k, bases) base scenes (with the plain shuffle two held-out scenes can share one base, and one
    image can carry a result); with False the split is the plain shuffle's.
    """
    names = sorted(set(scene_names))
    if set(fractions) != set(SPLITS):
        raise ConfigError(f"{SPLIT_KEY}: expected the keys {list(SPLITS)}, got {sorted(fractions)}")
    f = np.array([float(fractions[s]) for s in SPLITS])
    if (f <= 0).any() or not np.isfinite(f).all():
        raise ConfigError(f"{SPLIT_KEY}={dict(fractions)}: expected every fraction finite and > 0")
    if len(names) < 3:
        raise ConfigError(
            f"{SPLIT_KEY}: need at least 3 scenes to split into train/val/test, got {len(names)}: {names}"
        )
    f = f / f.sum()
    n = len(names)
    n_val, n_test = (max(1, round(x * n)) for x in f[1:])
    while n - n_val - n_test < 1:  # give train its one scene back from the larger held-out split
        if n_val >= n_test:
            n_val -= 1
        else:
            n_test -= 1
    order = [names[i] for i in np.random.default_rng(seed).permutation(n)]
    if by_base:
        order = _interleave_bases(order)
    parts = {"val": order[:n_val], "test": order[n_val : n_val + n_test], "train": order[n_val + n_test :]}
    return {s: sorted(parts[s]) for s in SPLITS}


def patch_quota(n_images: int, total: int) -> list[int]:
    """How many patches each of `n_images` images gives so that a split holds exactly `total`: an even
    share, the first `total % n_images` images one more (the seed thesis states a patch count, 16,867
    split 80/20, not a per-image one: Bunjevac 2019, Sec. 6)."""
    if n_images < 1:
        raise ConfigError(f"dataset.preprocess.patches_per_split: a split with {total} patches has no images")
    share, extra = divmod(int(total), n_images)
    return [share + (i < extra) for i in range(n_images)]
