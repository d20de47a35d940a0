"""Render the volumetric dataset (``dataset=volumetric``) as animated sequences.

Every scene of ``src.render.volume_scenes`` (``scenes_per_base`` seeds of each base) is an animation of
``dataset.frames`` frames; each frame is rendered by the volumetric path tracer (``nrbench_volpath``) at
every noisy sample count and at the reference count, one EXR per (scene, frame, spp) in
``src.data.volume_buffers.VOLUME_LAYOUT``: ``<raw_dir>/<scene>-f<FFFF>-<NNNNN>spp.exr``.

Seeds: each pass has its own seed from (dataset seed, scene, spp, role, pass, frame) (``pass_seed``), so
the reference is independent of the noisy renders and no two frames share random numbers.

Second reference (``dataset.second_reference``): the held-out scenes (val and test, as preprocessing
splits them: the caller passes them, ``src.kinds.sequences.held_out_scenes``) are rendered once more at
the reference count with the role ``reference2`` (other pass seeds, so its Monte Carlo noise is independent
of the first reference's), into ``<raw_dir>/reference2/`` (``SECOND_REFERENCE_DIR``). Two independent
references let the evaluation estimate the flicker against the noise-free truth
(``src.metrics.temporal.flicker_unbiased``). Only the held-out scenes: only their whole sequences are
evaluated, and at the cpu profile the references are 90% of the render time (the held-out four of the
eight scenes' references: +30% in all, against +90% for every scene). What decides the split
(``task.preprocess.split``, ``split_seed``, ``split_by_base``) decides which second references are
rendered, not what any of them holds, so it is not in a file's render key: a change of split renders the
newly held-out scenes' second references and keeps those of scenes no longer held out. Kept, because
preprocessing reads the held-out scenes' files by name (an extra file is never mixed in), and the two
tasks on these data split differently (task=filter_search sets ``split_by_base``): removing them would
render the costliest files again every time the other task renders into the same folder. Stale are second
references of scenes, frames or a reference count the dataset no longer has, and all of them when the
option is off (``remove_stale_volume_files``).

Motion: ``motion`` (``frame_motion``) is the flow in pixels from this frame to the next, computed from the
file's own mean ``position`` buffer with the cameras of frames t and t+1.

Caching and fan-out: each EXR has a manifest entry of its own, ``<raw_dir>/manifest/<file>.json`` holding
its render key (scene, size, spp, role, frame, seeds, integrator, layout), written atomically after the
EXR. A file whose entry holds the current key is kept. Since no two files share an entry, jobs rendering
different subsets (``scenes``, ``frames``) into one folder at once never overwrite each other's records,
and the subsets together give the same files as one run.
"""

from __future__ import annotations

import json
import time
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from src.data.volume_buffers import (
    SECOND_REFERENCE_DIR,
    VOLUME_EXR_BUFFERS,
    volume_exr_name,
    write_volume_exr,
)
from src.errors import ConfigError, DataError
from src.io.atomic import atomic_write_json
from src.render.render_dataset import (
    RenderTotals,
    SceneSource,
    box_film,
    pass_seed,
    render_key,
    scene_sources,
    split_passes,
    spp_counts,
)
from src.render.stale_renders import remove_stale_entries, restore_entry
from src.render.volume_camera import Camera, motion_vectors
from src.render.volume_scenes import camera_at

#: The integrator plugin every volumetric file is rendered with (``src.render.volpath_integrator``).
INTEGRATOR = "nrbench_volpath"
#: Folder of ``raw_dir`` (and of its ``reference2/``) holding one manifest entry per EXR.
MANIFEST_DIR = "manifest"
#: The role (``pass_seed``, the render key) of the second reference's files.
SECOND_REFERENCE_ROLE = "reference2"


def frame_motion(position: np.ndarray, camera_t: Camera, camera_t1: Camera | None) -> np.ndarray:
    """(H, W, 2) float32 flow in pixels from frame t to t+1 (+x right, +y down) of the points in
    ``position`` (H, W, 3), the mean world position of a pixel's first scattering surface or first medium
    collision (``volpath_integrator``): the pixel at p in frame t shows its point at p + flow in t+1.

    Conventions: 0 where the flow is undefined, i.e. where ``motion_vectors`` gives NaN (the point is
    behind either camera or not finite) or where no sample found a point (``position`` is exactly 0, sky
    seen through empty space); and 0 everywhere on the last frame (``camera_t1`` None: no next frame).
    Only the camera's motion is included, not the media's drift. Where only some samples found a point
    (silhouettes, thin media) the mean position is pulled towards the origin, so the flow there is
    approximate."""
    position = np.asarray(position, np.float64)
    height, width = position.shape[:2]
    if camera_t1 is None:
        return np.zeros((height, width, 2), np.float32)
    flow = motion_vectors(position, camera_t, camera_t1, width, height)
    undefined = ~np.isfinite(flow).all(-1) | ~np.any(position != 0.0, axis=-1)
    flow[undefined] = 0.0
    return flow.astype(np.float32)


def select_scenes(sources: list[SceneSource], names: Sequence[str] | None) -> list[SceneSource]:
    """The sources named in ``names`` (None: all), in dataset order; a ConfigError for an unknown name."""
    if names is None:
        return sources
    known = {s.name for s in sources}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ConfigError(
            f"dataset.render_scenes: unknown scene(s) {unknown}; the dataset has {sorted(known)}"
        )
    wanted = set(names)
    return [s for s in sources if s.name in wanted]


def select_frames(ds: Mapping, frames: Sequence[int] | None) -> list[int]:
    """The frames in ``frames`` (None: all of ``dataset.frames``), sorted; a ConfigError outside them."""
    n = int(ds["frames"])
    if frames is None:
        return list(range(n))
    bad = [f for f in frames if not 0 <= int(f) < n]
    if bad:
        raise ConfigError(f"dataset.render_frames: frame(s) {bad} outside the animation's frames 0-{n - 1}")
    return sorted({int(f) for f in frames})


def volume_render_key(source: SceneSource, ds: Mapping, frame: int, spp: int, role: str) -> str:
    """`render_key` of one volumetric file: also its frame, whether it is the last (its motion is 0), the
    grid resolution, the integrator plugin and the EXR layout (a new buffer renders everything again)."""
    extra = {
        "frame": frame,
        "last_frame": frame == int(ds["frames"]) - 1,
        "grid_res": ds["grid_res"],
        "integrator_type": INTEGRATOR,
        "layout": {b: list(c) for b, c in VOLUME_EXR_BUFFERS.items()},
    }
    return render_key(source.identity(), ds, spp, role, extra)


def frame_jobs(ds: Mapping, scene: str, second_reference: Collection[str] = ()) -> list[tuple[int, str]]:
    """The (spp, role) files of every frame of ``scene``: each noisy count, the reference, and the second
    reference (role ``reference2``, at the reference count) when ``scene`` is in ``second_reference``."""
    noisy, reference = spp_counts(ds)
    jobs = [(spp, "noisy") for spp in noisy] + [(reference, "reference")]
    if scene in second_reference:
        jobs.append((reference, SECOND_REFERENCE_ROLE))
    return jobs


def planned_file(source: SceneSource, ds: Mapping, frame: int, spp: int, role: str) -> dict:
    """One file of the dataset: its path relative to the raw folder (a second reference's under
    ``SECOND_REFERENCE_DIR``), scene, frame, spp, role, render key, passes and their seeds."""
    name = volume_exr_name(source.name, frame, spp)
    passes = split_passes(spp, int(ds["width"]) * int(ds["height"]), int(ds["max_pass_samples"]))
    return {
        "file": f"{SECOND_REFERENCE_DIR}/{name}" if role == SECOND_REFERENCE_ROLE else name,
        "scene": source.name,
        "frame": frame,
        "spp": spp,
        "role": role,
        "key": volume_render_key(source, ds, frame, spp, role),
        "passes": passes,
        "seeds": [pass_seed(int(ds["seed"]), source.name, spp, role, i, frame) for i in range(len(passes))],
    }


def render_plan(
    ds: Mapping,
    scenes: Sequence[str] | None = None,
    frames: Sequence[int] | None = None,
    second_reference: Collection[str] = (),
) -> list[dict]:
    """Every file (``planned_file``) a render of ``scenes`` x ``frames`` (None: all) makes, in render order
    (scene, frame, then ``frame_jobs``); the second references of the scenes in ``second_reference``."""
    sources = select_scenes(scene_sources(ds), scenes)
    frame_list = select_frames(ds, frames)
    return [
        planned_file(source, ds, frame, spp, role)
        for source in sources
        for frame in frame_list
        for spp, role in frame_jobs(ds, source.name, second_reference)
    ]


def _entry_path(raw_dir: Path, file: str) -> Path:
    """The manifest entry of ``file`` (relative to ``raw_dir``): ``manifest/<name>.json`` beside it."""
    path = Path(file)
    return raw_dir / path.parent / MANIFEST_DIR / f"{path.name}.json"


def _is_current(raw_dir: Path, file: str, key: str) -> bool:
    try:
        entry = json.loads(_entry_path(raw_dir, file).read_text())
    except (OSError, ValueError):
        return False
    return entry.get("key") == key and (raw_dir / file).exists()


def load_volume_frame(source: SceneSource, frame: int, ds: Mapping):
    """The Mitsuba scene of one frame, with the dataset's box-filtered film and an independent sampler."""
    import mitsuba as mi

    from src.render.volume_scenes import build_volumetric_frame

    scene = build_volumetric_frame(source.base, source.seed, frame, ds)
    scene["sensor"] = {**scene["sensor"], "film": box_film(ds), "sampler": {"type": "independent"}}
    try:
        return mi.load_dict(scene)
    except RuntimeError as err:
        first_line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise DataError(
            f"{source.name} frame {frame}: Mitsuba could not load the scene: {first_line}"
        ) from err


def remove_stale_volume_files(ds: Mapping, raw_dir: Path, second_reference: bool) -> list[str]:
    """Delete the files (and manifest entries) of ``raw_dir`` that the whole dataset no longer makes: in
    ``raw_dir`` those of no (scene, frame, spp) of ``ds``; in ``raw_dir/reference2`` those of no (scene,
    frame) of ``ds`` at its reference count, and every one when ``second_reference`` is off (those of
    scenes another split holds out stay: module docstring). Returns the names removed (``reference2/``
    ones with that prefix). Files without a manifest entry (a user's own) stay (``remove_stale_entries``)."""
    _, reference = spp_counts(ds)
    every_frame = range(int(ds["frames"]))
    every_file = {
        volume_exr_name(s.name, f, spp)
        for s in scene_sources(ds)
        for f in every_frame
        for spp, _ in frame_jobs(ds, s.name)
    }
    every_second = {
        volume_exr_name(s.name, f, reference)
        for s in scene_sources(ds)
        for f in every_frame
        if second_reference
    }
    removed = remove_stale_entries(raw_dir, MANIFEST_DIR, every_file)
    second_dir = raw_dir / SECOND_REFERENCE_DIR
    return removed + [
        f"{SECOND_REFERENCE_DIR}/{n}" for n in remove_stale_entries(second_dir, MANIFEST_DIR, every_second)
    ]


def render_frame_files(
    source: SceneSource,
    frame: int,
    ds: Mapping,
    files: list[dict],
    integrator,
    raw_dir: Path,
    totals: RenderTotals,
) -> float:
    """Render the ``files`` (``planned_file``) of one frame that are not current, each written as its EXR
    with its manifest entry after it; the frame's scene is built only if something renders. Returns the
    seconds spent building the scene (grids, Mitsuba load)."""
    from src.render.volume_film import render_volume_buffers

    pixels = int(ds["width"]) * int(ds["height"])
    build_seconds, scene = 0.0, None
    last = frame == int(ds["frames"]) - 1
    for file in files:
        spp, key, passes, seeds = file["spp"], file["key"], file["passes"], file["seeds"]
        if _is_current(raw_dir, file["file"], key):
            totals.skipped += 1
            continue
        where = Path(file["file"])  # reference2/<name> for a second reference
        if restore_entry(raw_dir / where.parent, MANIFEST_DIR, where.name, key):  # another config's
            totals.skipped += 1
            totals.restored += 1
            continue
        if scene is None:
            start = time.perf_counter()
            scene = load_volume_frame(source, frame, ds)
            build_seconds += time.perf_counter() - start
            cameras = (
                camera_at(source.base, source.seed, frame, ds),
                None if last else camera_at(source.base, source.seed, frame + 1, ds),
            )
        start = time.perf_counter()
        buffers = render_volume_buffers(scene, integrator, spp, seeds, passes)
        seconds = time.perf_counter() - start
        totals.seconds += seconds
        totals.samples += pixels * spp
        buffers["motion"] = frame_motion(buffers["position"], *cameras)
        (raw_dir / file["file"]).parent.mkdir(parents=True, exist_ok=True)
        write_volume_exr(raw_dir / file["file"], buffers)
        entry = {"key": key, "scene": source.name, "frame": frame, "spp": spp, "role": file["role"]}
        atomic_write_json(
            _entry_path(raw_dir, file["file"]),
            {**entry, "seeds": seeds, "passes": passes, "seconds": round(seconds, 3)},
        )
        totals.rendered += 1
    return build_seconds


def render_volumetric_dataset(
    ds: Mapping,
    raw_dir: Path,
    variant: str = "auto",
    scenes: Sequence[str] | None = None,
    frames: Sequence[int] | None = None,
    second_reference: Collection[str] = (),
) -> dict:
    """Render every (scene, frame) at every noisy spp and the reference into ``raw_dir``, and the second
    reference of the scenes in ``second_reference`` into ``raw_dir/reference2``; returns a summary.

    ``scenes`` (scene names, e.g. ``cloud-0000``) and ``frames`` (frame indices) select a subset, None: all
    of them; subsets rendered by separate (even concurrent) jobs compose to the files of one full run.
    Files whose manifest entry holds the current render key are kept; files with an entry that the whole
    dataset (every scene and frame, whatever the subset) no longer has are deleted first
    (``remove_stale_entries``: files without an entry, a user's own, stay); so are all second references
    when ``second_reference`` is empty (``dataset.second_reference`` off; ``remove_stale_volume_files``).
    """
    import mitsuba as mi

    from src.render.backend import set_mitsuba_variant

    second = frozenset(second_reference)
    plan = render_plan(ds, scenes, frames, second)
    variant = set_mitsuba_variant(variant)
    from src.render.volpath_integrator import register  # defines Mitsuba classes: needs the variant set

    register()
    integrator = mi.load_dict({"type": INTEGRATOR, **dict(ds["integrator"])})
    raw_dir.mkdir(parents=True, exist_ok=True)
    removed = remove_stale_volume_files(ds, raw_dir, bool(second))

    sources = {s.name: s for s in scene_sources(ds)}
    units: dict[tuple[str, int], list[dict]] = {}
    for file in plan:
        units.setdefault((file["scene"], file["frame"]), []).append(file)
    totals, build_seconds = RenderTotals(), 0.0
    for (scene, frame), files in tqdm(units.items(), desc=f"render volumetric [{variant}]", unit="frame"):
        build_seconds += render_frame_files(sources[scene], frame, ds, files, integrator, raw_dir, totals)
    return {
        "variant": variant,
        "scenes": list(dict.fromkeys(f["scene"] for f in plan)),
        "frames": select_frames(ds, frames),
        "second_reference": sorted({f["scene"] for f in plan if f["role"] == SECOND_REFERENCE_ROLE}),
        "files_rendered": totals.rendered,
        "files_cached": totals.skipped,
        "files_restored": totals.restored,
        "files_removed": len(removed),
        "samples": totals.samples,
        "render_seconds": round(totals.seconds, 3),
        "scene_build_seconds": round(build_seconds, 3),
        "samples_per_second": totals.samples / totals.seconds if totals.seconds > 0 else None,
    }
