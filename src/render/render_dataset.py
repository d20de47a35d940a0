"""Render the Monte Carlo denoising dataset: noisy sample counts and an independent reference per scene.

Each scene (procedural, or a user's Mitsuba scene file) is rendered through the same AOV integrator
with a box-filtered film, once per noisy sample count and once at the reference count, and written as
one EXR per (scene, spp) in the KPCN/Tungsten channel naming: ``<raw_dir>/<scene>-<NNNNN>spp.exr``.

Seeds: every pass of every render gets its own seed from a hash of (dataset seed, scene, spp, role,
pass), so no two renders share random numbers; in particular the reference is independent of the
noisy inputs. Large sample counts are split into passes so a wavefront never exceeds
``max_pass_samples`` samples (bounded memory at 1280x720 x 8192 spp).
"""

from __future__ import annotations

import hashlib
import json
import time
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from src.data.splits import exr_name
from src.errors import ConfigError, DataError
from src.io.atomic import atomic_write_json
from src.render.moments import MomentAccumulator, variance_of_mean
from src.render.stale_renders import remove_stale_files, restore_file

#: Each role's part of a pass seed (`pass_seed`): ``reference2`` is the volumetric sequences' second,
#: independent reference of the held-out scenes (``dataset.second_reference``); ``ladder`` the held-out
#: scenes' plain renders at ``dataset.ladder_spp`` (`src.data.ladder`).
ROLE_IDS = {"noisy": 1, "reference": 2, "reference2": 3, "ladder": 4}


@dataclass(frozen=True)
class SceneSource:
    """One scene of the dataset: a procedural (base, seed) or a user scene file."""

    name: str
    base: str | None = None
    seed: int | None = None
    path: Path | None = None

    def identity(self) -> dict:
        """What determines the scene's content (used in the cache key)."""
        if self.path is not None:
            return {"file": str(self.path), "sha256": hashlib.sha256(self.path.read_bytes()).hexdigest()}
        return {"base": self.base, "seed": self.seed}


def scene_sources(ds: Mapping) -> list[SceneSource]:
    """The dataset's scenes: ``scenes_per_base`` permutations of each base, then user scene files."""
    sources = []
    for b, base in enumerate(ds["bases"]):
        for i in range(int(ds["scenes_per_base"])):
            seed = int(np.random.SeedSequence([int(ds["seed"]), b, i]).generate_state(1)[0])
            sources.append(SceneSource(name=f"{base}-{i:04d}", base=base, seed=seed))
    for file in ds.get("scene_files") or []:
        path = Path(file)
        if not path.is_file():
            raise DataError(f"dataset.scene_files: scene file '{path}' not found")
        sources.append(SceneSource(name=path.stem.replace("_", "-"), path=path))
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        raise ConfigError(f"dataset: scene names are not unique: {sorted(names)}")
    return sources


def pass_seed(
    dataset_seed: int, scene: str, spp: int, role: str, pass_index: int, frame: int | None = None
) -> int:
    """A 32-bit sampler seed unique to (dataset seed, scene, spp, role, pass[, frame of a sequence]).
    Without a frame the key is that of the still-image datasets (their seeds do not change)."""
    key = [dataset_seed, zlib.crc32(scene.encode()), spp, ROLE_IDS[role], pass_index]
    if frame is not None:
        key.append(int(frame))
    return int(np.random.SeedSequence(key).generate_state(1)[0])


def split_passes(spp: int, pixels: int, max_pass_samples: int) -> list[int]:
    """Split ``spp`` into passes of at most ``max_pass_samples // pixels`` samples per pixel (>= 2)."""
    per_pass = max(2, min(spp, max_pass_samples // max(pixels, 1)))
    passes = [per_pass] * (spp // per_pass)
    if spp % per_pass:
        passes.append(spp % per_pass)
    return passes


def load_scene(source: SceneSource, ds: Mapping):
    """Load the Mitsuba scene and build a box-filtered sensor that reuses the scene camera."""
    import mitsuba as mi

    from src.render.scenes import build_procedural_scene

    try:
        if source.path is not None:
            scene = mi.load_file(str(source.path))
        else:
            scene = mi.load_dict(build_procedural_scene(source.base, source.seed, ds))
    except RuntimeError as err:
        first_line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise DataError(
            f"{source.path or source.name}: Mitsuba could not load the scene: {first_line}"
        ) from err
    if not scene.sensors():
        raise DataError(f"{source.path or source.name}: the scene has no sensor (camera)")
    params = mi.traverse(scene.sensors()[0])
    if "x_fov" not in params:
        raise DataError(f"{source.path or source.name}: only perspective cameras are supported")
    matrix = np.array(params["to_world"].matrix).reshape(4, 4)
    sensor = mi.load_dict(
        {
            "type": "perspective",
            "fov_axis": "x",
            "fov": float(np.array(params["x_fov"]).ravel()[0]),
            "to_world": mi.ScalarTransform4f(matrix),
            "film": box_film(ds),
            "sampler": {"type": "independent"},
        }
    )
    return scene, sensor


def box_film(ds: Mapping) -> dict:
    """The dataset's film: ``width`` x ``height``, float32 RGB (plus the integrator's AOVs), box filter."""
    return {
        "type": "hdrfilm",
        "width": int(ds["width"]),
        "height": int(ds["height"]),
        "rfilter": {"type": "box"},  # one sample -> one pixel, so film means are exact sample means
        "pixel_format": "rgb",
        "component_format": "float32",
    }


def render_buffers(scene, sensor, integrator, spp: int, seeds: list[int], passes: list[int]) -> dict:
    """Render ``spp`` samples in ``passes``; returns KPCN buffers (H, W, C) float32 incl. variances (left
    out at 1 spp, which has none: the ladder's 1-spp rung keeps only its colour)."""
    import mitsuba as mi

    from src.render.aov_integrator import AOV_BUFFERS, CHANNEL_COUNT, MOMENT_BUFFERS

    acc = MomentAccumulator()
    for seed, n in zip(seeds, passes, strict=True):
        acc.add(np.asarray(mi.render(scene, sensor=sensor, integrator=integrator, spp=n, seed=seed)), n)
    img = acc.mean()
    offsets, start = {}, 0
    for buf in ("color", *AOV_BUFFERS):  # film layout: RGB, then the AOVs in integrator order
        offsets[buf] = (start, start + CHANNEL_COUNT[buf])
        start += CHANNEL_COUNT[buf]
    buffers = {buf: img[..., a:b].astype(np.float32) for buf, (a, b) in offsets.items()}
    for buf in MOMENT_BUFFERS:
        a, b = offsets[buf]
        second = img[..., start : start + (b - a)]
        start += b - a
        if spp >= 2:
            buffers[f"{buf}Variance"] = variance_of_mean(img[..., a:b], second, spp).astype(np.float32)
    return buffers


def render_key(scene_identity: dict, ds: Mapping, spp: int, role: str, extra: Mapping | None = None) -> str:
    """Hash of everything that determines one output file, to skip renders whose output is current.

    ``scene_identity`` is ``SceneSource.identity()``; procedural scenes also depend on ``randomize`` and
    on their base scene's ``base_scenes.<base>`` constants. ``extra``: what else a kind of data depends
    on (a sequence's frame, its integrator and layout), hashed with the rest.
    """
    keyed = {k: ds[k] for k in ("width", "height", "seed", "integrator", "max_pass_samples")}
    payload = {"scene": scene_identity, "spp": spp, "role": role, **keyed}
    if extra:
        payload["extra"] = dict(extra)
    if "base" in scene_identity:
        payload["randomize"] = ds["randomize"]
        payload["base_scene"] = (ds.get("base_scenes") or {}).get(scene_identity["base"])
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:16]


def still_image_key_extra() -> dict:
    """What else a still-image file depends on: the buffers the integrator writes (so files rendered before
    `position` / `secondary_albedo` were added are rendered again)."""
    from src.render.aov_integrator import AOV_BUFFERS

    return {"buffers": list(AOV_BUFFERS)}


@dataclass
class RenderTotals:
    """What a dataset render did: samples and seconds rendered, files rendered and files kept (of which
    `restored` were moved back from `.parked/`, `src.render.stale_renders`)."""

    samples: int = 0
    seconds: float = 0.0
    rendered: int = 0
    skipped: int = 0
    restored: int = 0


def render_denoise_dataset(ds: Mapping, raw_dir: Path, variant: str = "auto") -> dict:
    """Render every scene at every noisy spp and the reference into ``raw_dir``; returns a summary.

    Files whose render key (scene, size, spp, seeds, integrator) matches ``manifest.json`` are kept,
    so re-running with the same config renders nothing and a changed config renders only what changed;
    files the manifest lists that the config does not make (another spp, a scene of another task's
    config) are set aside into ``.parked/`` first, and moved back when a config needs them again
    (``remove_stale_files``, ``restore_file``: a user's own EXRs, which it does not list, stay).
    """
    import mitsuba as mi

    from src.render.backend import set_mitsuba_variant

    noisy, reference = spp_counts(ds)
    variant = set_mitsuba_variant(variant)
    integrator = mi.load_dict({"type": "kpcn_aov", **dict(ds["integrator"])})
    raw_dir.mkdir(parents=True, exist_ok=True)
    jobs = [(spp, "noisy") for spp in noisy] + [(reference, "reference")]
    sources = scene_sources(ds)
    removed = remove_stale_files(raw_dir, {exr_name(s.name, spp) for s in sources for spp, _ in jobs})
    manifest_path = raw_dir / "manifest.json"
    manifest = json.loads(manifest_path.read_text()) if manifest_path.exists() else {}

    totals = RenderTotals()
    for source in tqdm(sources, desc=f"render [{variant}]", unit="scene"):
        render_scene_files(source, ds, jobs, integrator, raw_dir, manifest, totals)
    return {
        "variant": variant,
        "scenes": len(sources),
        "files_rendered": totals.rendered,
        "files_cached": totals.skipped,
        "files_restored": totals.restored,
        "files_removed": len(removed),
        "samples": totals.samples,
        "render_seconds": round(totals.seconds, 3),
        "samples_per_second": totals.samples / totals.seconds if totals.seconds > 0 else None,
    }


def spp_counts(ds: Mapping) -> tuple[list[int], int]:
    """The sorted noisy sample counts and the reference count; a `ConfigError` unless every noisy count is
    >= 2 and the reference is above them all (also the dataset schema's check, at job start)."""
    noisy = sorted(int(s) for s in ds["noisy_spp"])
    reference = int(ds["reference_spp"])
    if not noisy or min(noisy) < 2:
        raise ConfigError(f"dataset.noisy_spp={noisy}: expected sample counts >= 2")
    if reference <= max(noisy):
        raise ConfigError(
            f"dataset.reference_spp={reference}: expected more than the largest noisy_spp ({max(noisy)}) of "
            f"dataset.noisy_spp={noisy}; the reference is the highest sample count of a scene"
        )
    return noisy, reference


def render_scene_files(
    source: SceneSource,
    ds: Mapping,
    jobs: list[tuple[int, str]],
    integrator,
    raw_dir: Path,
    manifest: dict,
    totals: RenderTotals,
) -> None:
    """Render the (spp, role) ``jobs`` of one scene whose file is not current, each written as its EXR and
    recorded in ``manifest`` (saved after every file); the scene is loaded only if something renders."""
    from src.data.kpcn_buffers import write_kpcn_exr

    pixels = int(ds["width"]) * int(ds["height"])
    scene = sensor = None
    identity = source.identity()
    for spp, role in jobs:
        name = exr_name(source.name, spp)
        key = render_key(identity, ds, spp, role, still_image_key_extra())
        if manifest.get(name) == key and (raw_dir / name).exists():
            totals.skipped += 1
            continue
        if restore_file(raw_dir, name, key, manifest):  # set aside by another config's render
            totals.skipped += 1
            totals.restored += 1
            continue
        if scene is None:
            scene, sensor = load_scene(source, ds)
        passes = split_passes(spp, pixels, int(ds["max_pass_samples"]))
        seeds = [pass_seed(int(ds["seed"]), source.name, spp, role, i) for i in range(len(passes))]
        start = time.perf_counter()
        buffers = render_buffers(scene, sensor, integrator, spp, seeds, passes)
        totals.seconds += time.perf_counter() - start
        totals.samples += pixels * spp
        write_kpcn_exr(raw_dir / name, buffers)
        manifest[name] = key
        atomic_write_json(raw_dir / "manifest.json", manifest)
        totals.rendered += 1
