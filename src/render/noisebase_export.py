"""Export the volumetric sequences (`dataset=volumetric`, `src.render.volume_dataset`) as Noisebase sample
sets (issue 35; docs/noisebase.md): per-sample buffers for methods built on the `noisebase` package
(Balint et al. 2023).

nrbench's renders keep per-pixel means, so the per-sample values are made as the format needs them: each
sample is its own 1-spp render of the frame with a distinct seed (`pass_seed` of the scene, the sample
index and the frame, with the noisy role at 1 spp, a count no noisy file has), whose colour, position,
normal and albedo are that sample's. The clean `reference` is the frame rendered at
`dataset.reference_spp` with the reference files' own passes and seeds (`planned_file`), so it is the
reference of the volumetric raw data. The camera (`noisebase_camera`) is the frame's Mitsuba look-at
camera as Noisebase's position / target / up and a DirectX projection of its horizontal field of view.
World `motion` is 0: the surfaces are static and only the camera moves (the media drift, but a medium
sample's scattering position is random per sample, so it has no motion to carry).

The still-image family (`dataset=procedural`, `src.render.render_dataset`) has no animation: it is exported
as short sequences of `frames` frames whose camera pans (`pan_deg` degrees per frame about the world's up
axis through the camera, so no scene scale is needed), each frame rendered per sample with the KPCN AOV
integrator (colour, world position, normal, albedo) in the same way (`export_still_sequences`).

The still-image family (`dataset=procedural`, `src.render.render_dataset`) has no animation: it is exported
as short sequences of `frames` frames whose camera pans (`pan_deg` degrees per frame about the world's up
axis through the camera, so no scene scale is needed), each frame rendered per sample with the KPCN AOV
integrator (colour, world position, normal, albedo) in the same way (`export_still_sequences`).

Written with `src.data.noisebase_export`: a training-format store per sequence
(`<out>/scene{index:04d}.zip`, the sequences in dataset order) or test-format stores
(`<out>/<scene>/frame{index:04d}.zip`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from src.data.noisebase_export import (
    frame_arrays,
    projection_matrix,
    write_test_frame,
    write_training_sequence,
)
from src.errors import ConfigError
from src.render.render_dataset import pass_seed, scene_sources
from src.render.volume_camera import Camera
from src.render.volume_dataset import INTEGRATOR, load_volume_frame, planned_file
from src.render.volume_scenes import camera_at

#: Volumetric buffer -> Noisebase per-sample array (`color` is RGBE-encoded from `radiance`).
SAMPLE_BUFFERS = {"color": "radiance", "position": "position", "normal": "normal", "albedo": "diffuse"}


def noisebase_camera(camera: Camera, width: int, height: int) -> dict[str, np.ndarray]:
    """Noisebase's camera arrays of a Mitsuba look-at camera (columns of `to_world`: left, up, forward,
    origin; Noisebase's right = forward x up = -left): position, a target one unit ahead, up, and the
    projection of the horizontal field of view on a `width` x `height` frame."""
    to_world = np.asarray(camera.to_world, np.float64)
    position = to_world[:3, 3]
    return {
        "camera_position": position,
        "camera_target": position + to_world[:3, 2],
        "camera_up": to_world[:3, 1],
        "proj_mat": projection_matrix(float(camera.fov), width, height),
    }


def frame_samples(render, source_name: str, ds: Mapping, frame: int, spp: int) -> dict[str, np.ndarray]:
    """(C, H, W, spp) per-sample buffers of one frame: `spp` 1-spp renders `render(seed)` (-> buffers
    (H, W, C)) with distinct seeds."""
    renders = [render(pass_seed(int(ds["seed"]), source_name, 1, "noisy", s, frame)) for s in range(spp)]
    return {
        ours: np.stack([np.moveaxis(r[buffer], -1, 0) for r in renders], -1)
        for buffer, ours in SAMPLE_BUFFERS.items()
    }


def _selected(ds: Mapping, fmt: str, spp: int, scenes: Sequence[str] | None) -> list:
    """The dataset's scene sources named in `scenes` (None: all), after checking the format and count."""
    if fmt not in ("training", "test"):
        raise ConfigError(f"noisebase export: format {fmt!r}; expected training or test")
    if spp < 1:
        raise ConfigError(f"noisebase export: spp={spp}; expected at least 1 sample per pixel")
    sources = scene_sources(dict(ds))
    if scenes is not None:
        unknown = sorted(set(scenes) - {s.name for s in sources})
        if unknown:
            raise ConfigError(
                f"noisebase export: unknown scene(s) {unknown}; the dataset has {[s.name for s in sources]}"
            )
        sources = [s for s in sources if s.name in set(scenes)]
    return sources


def _write(out: Path, fmt: str, index: int, name: str, frames: list[dict]) -> list[Path]:
    """A training store `scene{index:04d}.zip`, or a test store per frame `<name>/frame{f:04d}.zip`."""
    if fmt == "training":
        return [write_training_sequence(out / f"scene{index:04d}.zip", frames)]
    return [write_test_frame(out / name / f"frame{f:04d}.zip", a) for f, a in enumerate(frames)]


def export_volumetric_sequences(
    ds: Mapping, out: Path, fmt: str, spp: int, scenes: Sequence[str] | None = None, variant: str = "auto"
) -> list[Path]:
    """Write every frame of the `scenes` (names; None: all of `ds`'s) with `spp` samples per pixel as a
    Noisebase `fmt` ("training" | "test") set under `out`; returns the stores written."""
    import mitsuba as mi

    from src.render.backend import set_mitsuba_variant

    sources = _selected(ds, fmt, spp, scenes)
    set_mitsuba_variant(variant)
    from src.render.volpath_integrator import register  # defines Mitsuba classes: needs the variant set
    from src.render.volume_film import render_volume_buffers

    register()
    integrator = mi.load_dict({"type": INTEGRATOR, **dict(ds["integrator"])})
    width, height, reference_spp = int(ds["width"]), int(ds["height"]), int(ds["reference_spp"])
    rng = np.random.default_rng(int(ds["seed"]))  # the RGBE dither
    written = []
    for index, source in enumerate(sources):
        frames = []
        for frame in range(int(ds["frames"])):
            scene = load_volume_frame(source, frame, ds)
            samples = frame_samples(
                lambda seed, scene=scene: render_volume_buffers(scene, integrator, 1, [seed]),
                source.name,
                ds,
                frame,
                spp,
            )
            samples["motion"] = np.zeros_like(samples["position"])
            plan = planned_file(source, ds, frame, reference_spp, "reference")
            reference = render_volume_buffers(scene, integrator, reference_spp, plan["seeds"], plan["passes"])
            camera = noisebase_camera(camera_at(source.base, source.seed, frame, ds), width, height)
            frames.append(
                frame_arrays(
                    samples,
                    np.moveaxis(reference["color"], -1, 0),
                    camera,
                    [0, 0],
                    (height, width),
                    rng.random,
                )
            )
        written += _write(out, fmt, index, source.name, frames)
    return written


def still_sample(scene, sensor, integrator, seed: int) -> dict[str, np.ndarray]:
    """One sample per pixel of the KPCN AOV integrator: its film's colour and AOVs (H, W, C), split in the
    film's layout as `src.render.render_dataset.render_buffers` splits it (which needs >= 2 samples)."""
    import mitsuba as mi

    from src.render.aov_integrator import AOV_BUFFERS, CHANNEL_COUNT

    img = np.asarray(mi.render(scene, sensor=sensor, integrator=integrator, spp=1, seed=seed), np.float32)
    out, start = {}, 0
    for buf in ("color", *AOV_BUFFERS):
        out[buf] = img[..., start : start + CHANNEL_COUNT[buf]]
        start += CHANNEL_COUNT[buf]
    return out


def panned(to_world: np.ndarray, degrees: float) -> np.ndarray:
    """`to_world` turned by `degrees` about the world's +Y axis through the camera's origin (a pan)."""
    a = np.radians(degrees)
    rotation = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    out = np.array(to_world, np.float64)
    out[:3, :3] = rotation @ out[:3, :3]
    return out


def export_still_sequences(
    ds: Mapping,
    out: Path,
    fmt: str,
    spp: int,
    frames: int,
    pan_deg: float,
    scenes: Sequence[str] | None = None,
    variant: str = "auto",
) -> list[Path]:
    """The still-image scenes (`dataset=procedural`: procedural or a user's scene files) as `frames`-frame
    sequences whose camera pans by `pan_deg` per frame, written as a Noisebase `fmt` set under `out` (per
    sample: one 1-spp render with the KPCN AOV integrator; per frame, the reference at
    `dataset.reference_spp` with the still references' seed scheme and the frame)."""
    import mitsuba as mi

    from src.render.backend import set_mitsuba_variant
    from src.render.render_dataset import box_film, load_scene, render_buffers, split_passes

    if frames < 1:
        raise ConfigError(f"noisebase export: frames={frames}; expected at least 1")
    sources = _selected(ds, fmt, spp, scenes)
    set_mitsuba_variant(variant)  # also registers the kpcn_aov integrator
    integrator = mi.load_dict({"type": "kpcn_aov", **dict(ds["integrator"])})
    width, height, reference_spp = int(ds["width"]), int(ds["height"]), int(ds["reference_spp"])
    passes = split_passes(reference_spp, width * height, int(ds["max_pass_samples"]))
    rng = np.random.default_rng(int(ds["seed"]))  # the RGBE dither
    written = []
    for index, source in enumerate(sources):
        scene, sensor = load_scene(source, ds)
        params = mi.traverse(sensor)
        fov = float(np.array(params["x_fov"]).ravel()[0])
        start = np.array(params["to_world"].matrix).reshape(4, 4)
        arrays = []
        for frame in range(frames):
            camera = Camera(panned(start, pan_deg * frame), fov)
            moved = mi.load_dict(
                {**camera.sensor(), "film": box_film(ds), "sampler": {"type": "independent"}}
            )
            samples = frame_samples(
                lambda seed, scene=scene, moved=moved: still_sample(scene, moved, integrator, seed),
                source.name,
                ds,
                frame,
                spp,
            )
            samples["motion"] = np.zeros_like(samples["position"])
            seeds = [
                pass_seed(int(ds["seed"]), source.name, reference_spp, "reference", i, frame)
                for i in range(len(passes))
            ]
            reference = render_buffers(scene, moved, integrator, reference_spp, seeds, passes)["color"]
            arrays.append(
                frame_arrays(
                    samples,
                    np.moveaxis(reference, -1, 0),
                    noisebase_camera(camera, width, height),
                    [0, 0],
                    (height, width),
                    rng.random,
                )
            )
        written += _write(out, fmt, index, source.name, arrays)
    return written
