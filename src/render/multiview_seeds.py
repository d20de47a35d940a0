"""The splits of a multi-view dataset and the seeds of everything random in it: a scene's content, each
split's camera poses and each view's render passes, all derived from the dataset seed and the scene name."""

from __future__ import annotations

import zlib

import numpy as np

SPLITS = ("train", "val", "test")
SPLIT_IDS = {"train": 1, "val": 2, "test": 3}


def scene_seed(seed: int, scene: str, *extra: int) -> int:
    """A 32-bit seed unique to (dataset seed, scene name, extra integers...)."""
    return int(np.random.SeedSequence([int(seed), zlib.crc32(scene.encode()), *extra]).generate_state(1)[0])


def split_seed(seed: int, scene: str, split: str) -> int:
    """The seed of the camera poses of one split of one scene."""
    return scene_seed(seed, scene, SPLIT_IDS[split])
