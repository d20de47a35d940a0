"""Render the sample-count ladder of the held-out scenes (`src.data.ladder`: layout and reading).

Each data kind's render module supplies how a scene (a still, or one frame of a sequence) is loaded and how
one rung's colour is rendered, and the render key of a rung; this module plans the files, skips the current
ones, times and writes the others with their manifest entries, and removes the stale ones. The held-out
scenes are the caller's (the kind splits as its preprocessing will); as with the sequences' second
reference, a change of split renders the newly held-out scenes' ladders and keeps the others' (another task
on the same folder may hold them out), while rungs of a scene, frame or count the dataset no longer has are
deleted, and all of them when `dataset.ladder_spp` is empty.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from src.data.ladder import LADDER_ROLE, MANIFEST_DIR, entry_path, ladder_counts, ladder_file
from src.io.atomic import atomic_write_json
from src.io.exr import write_exr
from src.render.render_dataset import RenderTotals, SceneSource, pass_seed, split_passes
from src.render.stale_renders import remove_stale_entries, restore_entry

#: (source, frame or None, spp) -> the render key of that rung.
KeyOf = Callable[[SceneSource, "int | None", int], str]
#: (source, frame or None) -> whatever `RenderColor` needs of the loaded scene.
LoadScene = Callable[[Any, "int | None"], Any]
#: (loaded scene, spp, pass seeds, passes) -> (H, W, 3) float32 linear colour.
RenderColor = Callable[[Any, int, list[int], list[int]], np.ndarray]


def ladder_plan(
    ds: Mapping, sources: Sequence[SceneSource], frames: Sequence[int] | None, key_of: KeyOf
) -> list[dict]:
    """Every rung file of `sources` (each of `frames` of a sequence; None: still images): file, scene,
    frame, spp, render key, passes and their seeds (role ``ladder``: independent of every other render)."""
    pixels = int(ds["width"]) * int(ds["height"])
    indices: Sequence[int | None] = [None] if frames is None else frames
    plan = []
    for source in sources:
        for frame in indices:
            for spp in ladder_counts(ds):
                passes = split_passes(spp, pixels, int(ds["max_pass_samples"]))
                seeds = [
                    pass_seed(int(ds["seed"]), source.name, spp, LADDER_ROLE, i, frame)
                    for i in range(len(passes))
                ]
                plan.append(
                    {
                        "file": ladder_file(source.name, spp, frame),
                        "scene": source.name,
                        "frame": frame,
                        "spp": spp,
                        "key": key_of(source, frame, spp),
                        "passes": passes,
                        "seeds": seeds,
                    }
                )
    return plan


def _is_current(ladder_dir: Path, file: dict) -> bool:
    try:
        entry = json.loads(entry_path(ladder_dir, file["file"]).read_text())
    except (OSError, ValueError):
        return False
    return entry.get("key") == file["key"] and (ladder_dir / file["file"]).exists()


def remove_stale_ladder(
    ds: Mapping, ladder_dir: Path, every_scene: Sequence[str], frames: int | None
) -> list[str]:
    """Delete the rungs (and entries) of no scene in `every_scene` x frame x `dataset.ladder_spp` count (all
    of them when the ladder is empty); returns their names. Files without an entry stay."""
    indices: Sequence[int | None] = [None] if frames is None else range(frames)
    expected = {ladder_file(s, spp, f) for s in every_scene for f in indices for spp in ladder_counts(ds)}
    return remove_stale_entries(Path(ladder_dir), MANIFEST_DIR, expected)


def render_ladder(
    plan: list[dict],
    sources: Mapping[str, Any],
    load: LoadScene,
    render: RenderColor,
    ladder_dir: Path,
    desc: str,
    timed: bool = True,
) -> dict[str, Any]:
    """Render the `plan`'s files that are not current into `ladder_dir` (colour only, float32), each
    followed by its manifest entry (key, scene, frame, spp, seconds of the render passes: null unless
    `timed`, when `render` only averages stored samples); a scene (or frame) is loaded once and only if one
    of its rungs renders. Returns a summary."""
    ladder_dir = Path(ladder_dir)
    totals = RenderTotals()
    units: dict[tuple[str, int | None], list[dict]] = {}
    for file in plan:
        units.setdefault((file["scene"], file["frame"]), []).append(file)
    for (scene, frame), files in tqdm(units.items(), desc=desc, unit="image", disable=not units):
        loaded = None
        for file in files:
            if _is_current(ladder_dir, file):
                totals.skipped += 1
                continue
            if restore_entry(ladder_dir, MANIFEST_DIR, file["file"], file["key"]):  # another config's
                totals.skipped += 1
                totals.restored += 1
                continue
            if loaded is None:
                loaded = load(sources[scene], frame)
            start = time.perf_counter()
            color = render(loaded, file["spp"], file["seeds"], file["passes"])
            seconds = time.perf_counter() - start
            totals.seconds += seconds
            write_exr(
                ladder_dir / file["file"], {c: color[..., i].astype(np.float32) for i, c in enumerate("RGB")}
            )
            entry = {k: file[k] for k in ("key", "scene", "frame", "spp", "passes", "seeds")}
            entry["seconds"] = round(seconds, 4) if timed else None
            atomic_write_json(entry_path(ladder_dir, file["file"]), entry)
            totals.rendered += 1
    return {
        "scenes": sorted({f["scene"] for f in plan}),
        "counts": sorted({f["spp"] for f in plan}),
        "files_rendered": totals.rendered,
        "files_cached": totals.skipped,
        "files_restored": totals.restored,
        "render_seconds": round(totals.seconds, 3),
    }


def nothing_rendered(removed: Sequence[str]) -> dict[str, Any]:
    """The summary of a ladder render with nothing to render (after removing the stale rungs `removed`)."""
    return {"scenes": [], "counts": [], "files_rendered": 0, "files_cached": 0, "files_removed": len(removed)}


def render_still_ladder(
    ds: Mapping, ladder_dir: Path, held_out: Sequence[str], variant: str
) -> dict[str, Any]:
    """The ladder of the held-out still scenes `held_out`, through the dataset's own AOV integrator (its
    colour is the noisy inputs' estimator, and its seconds per sample are theirs)."""
    import mitsuba as mi

    from src.render.backend import set_mitsuba_variant
    from src.render.render_dataset import (
        load_scene,
        render_buffers,
        render_key,
        scene_sources,
        still_image_key_extra,
    )

    sources = {s.name: s for s in scene_sources(ds)}
    removed = remove_stale_ladder(ds, ladder_dir, list(sources), None)
    wanted = [sources[name] for name in held_out if name in sources]

    def key_of(source: SceneSource, frame: int | None, spp: int) -> str:
        return render_key(source.identity(), ds, spp, LADDER_ROLE, still_image_key_extra())

    plan = ladder_plan(ds, wanted, None, key_of)
    if not plan:  # no held-out scene, or no ladder: Mitsuba is not even set up
        return nothing_rendered(removed)
    set_mitsuba_variant(variant)
    integrator = mi.load_dict({"type": "kpcn_aov", **dict(ds["integrator"])})

    def render(loaded, spp: int, seeds: list[int], passes: list[int]) -> np.ndarray:
        scene, sensor = loaded
        return render_buffers(scene, sensor, integrator, spp, seeds, passes)["color"]

    summary = render_ladder(
        plan, sources, lambda s, f: load_scene(s, ds), render, ladder_dir, "render ladder"
    )
    return {**summary, "files_removed": len(removed)}


def render_sequence_ladder(
    ds: Mapping, ladder_dir: Path, held_out: Sequence[str], frames: Sequence[int], variant: str
) -> dict[str, Any]:
    """The ladder of every frame in `frames` of the held-out sequences `held_out`, through the volumetric
    path tracer the sequences are rendered with."""
    import mitsuba as mi

    from src.render.backend import set_mitsuba_variant
    from src.render.render_dataset import scene_sources
    from src.render.volume_dataset import INTEGRATOR, load_volume_frame, volume_render_key
    from src.render.volume_film import render_volume_buffers

    sources = {s.name: s for s in scene_sources(ds)}
    removed = remove_stale_ladder(ds, ladder_dir, list(sources), int(ds["frames"]))
    wanted = [sources[name] for name in held_out if name in sources]

    def key_of(source: SceneSource, frame: int | None, spp: int) -> str:
        return volume_render_key(source, ds, int(frame), spp, LADDER_ROLE)

    plan = ladder_plan(ds, wanted, list(frames), key_of)
    if not plan:  # no held-out scene, or no ladder: Mitsuba is not even set up
        return nothing_rendered(removed)
    set_mitsuba_variant(variant)
    from src.render.volpath_integrator import register  # defines Mitsuba classes: needs the variant set

    register()
    integrator = mi.load_dict({"type": INTEGRATOR, **dict(ds["integrator"])})

    def render(scene, spp: int, seeds: list[int], passes: list[int]) -> np.ndarray:
        return render_volume_buffers(scene, integrator, spp, seeds, passes)["color"]

    def load(source: SceneSource, frame: int | None):
        return load_volume_frame(source, int(frame), ds)

    summary = render_ladder(plan, sources, load, render, ladder_dir, "render ladder")
    return {**summary, "files_removed": len(removed)}


def noisebase_ladder(ds: Mapping, ladder_dir: Path, held_out: Sequence[str]) -> dict[str, Any]:
    """The ladder of every frame of the held-out Noisebase sequences `held_out`: nothing is rendered, each
    rung averages the last k of the first max(`dataset.ladder_spp`) stored samples
    (`src.data.noisebase.ladder_color`), so its entry has no render seconds and no speed-up is claimed. A
    rung's key is its store's stamp (path, size, time), frame, window and samples."""
    import hashlib

    from src.data.noisebase import ladder_color, read_frames, sequence_sources, source_stamp

    sources = sequence_sources(ds)
    removed = remove_stale_ladder(ds, ladder_dir, list(sources), int(ds["frames"]))
    counts = ladder_counts(ds)
    top = max(counts) if counts else 0
    window = {k: ds[k] for k in ("format", "crop", "rendering_height", "rendering_width")}
    stamps = {store: source_stamp([store]) for scene in held_out for store, _ in sources.get(scene, [])}

    def key_of(scene: str, frame: int, spp: int) -> str:
        store, index = sources[scene][frame]
        identity = [stamps[store], index, window, [top - spp, top]]
        return hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()

    plan = [
        {
            "file": ladder_file(scene, spp, frame),
            **{"scene": scene, "frame": frame, "spp": spp, "key": key_of(scene, frame, spp)},
            **{"passes": [], "seeds": []},
        }
        for scene in held_out
        if scene in sources
        for frame in range(len(sources[scene]))
        for spp in counts
    ]
    rendering = (int(ds["rendering_height"]), int(ds["rendering_width"]))

    def load(frames: list, frame: int | None):
        store, index = frames[int(frame)]
        return read_frames(store, ds["format"], [index], top, ds.get("crop"), rendering)[0]

    def average(frame, spp: int, seeds: list[int], passes: list[int]) -> np.ndarray:
        return ladder_color(frame, spp)

    summary = render_ladder(plan, sources, load, average, ladder_dir, "ladder from samples", timed=False)
    return {**summary, "files_removed": len(removed)}
