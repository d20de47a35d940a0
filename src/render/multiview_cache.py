"""The render cache of the multi-view scenes: a scene is skipped when its render key (scene, every config
value that changes its pixels, per-split seeds, ``FORMAT_VERSION``) equals the one stored in its
``nrbench_render.json``."""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path

from src.render.multiview_seeds import SPLITS, split_seed

#: The cache bookkeeping file inside each scene folder.
KEY_FILE = "nrbench_render.json"
#: Bump when the renderer's output changes for the same config (invalidates every cached scene).
FORMAT_VERSION = 1
#: Dataset keys that do not change any rendered pixel (kept out of the render key).
NON_PIXEL_KEYS = frozenset({"name", "scenes", "near", "far", "background", "scene_params", "root"})


def render_key(ds: Mapping, scene: str) -> str:
    """Hash of everything that decides the pixels and poses of ``scene``: the renderer version, the
    scene's parameters, every dataset value outside ``NON_PIXEL_KEYS`` and the per-split pose seeds."""
    payload = {
        "format_version": FORMAT_VERSION,
        "scene": scene,
        "scene_params": (ds.get("scene_params") or {}).get(scene),
        "split_seeds": {s: split_seed(int(ds["seed"]), scene, s) for s in SPLITS},
        **{k: v for k, v in ds.items() if k not in NON_PIXEL_KEYS},
    }
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _read_key(scene_dir: Path) -> str | None:
    try:
        return json.loads((scene_dir / KEY_FILE).read_text())["render_key"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def is_current(scene_dir: Path, key: str) -> bool:
    files = [scene_dir / f"transforms_{s}.json" for s in SPLITS]
    return _read_key(scene_dir) == key and all(f.is_file() for f in files)
