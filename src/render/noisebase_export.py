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


def frame_samples(
    scene, integrator, source_name: str, ds: Mapping, frame: int, spp: int
) -> dict[str, np.ndarray]:
    """(C, H, W, spp) per-sample buffers of one frame: `spp` 1-spp renders with distinct seeds."""
    from src.render.volume_film import render_volume_buffers

    renders = [
        render_volume_buffers(
            scene, integrator, 1, [pass_seed(int(ds["seed"]), source_name, 1, "noisy", s, frame)]
        )
        for s in range(spp)
    ]
    return {
        ours: np.stack([np.moveaxis(r[buffer], -1, 0) for r in renders], -1)
        for buffer, ours in SAMPLE_BUFFERS.items()
    }


def export_volumetric_sequences(
    ds: Mapping, out: Path, fmt: str, spp: int, scenes: Sequence[str] | None = None, variant: str = "auto"
) -> list[Path]:
    """Write every frame of the `scenes` (names; None: all of `ds`'s) with `spp` samples per pixel as a
    Noisebase `fmt` ("training" | "test") set under `out`; returns the stores written."""
    import mitsuba as mi

    from src.render.backend import set_mitsuba_variant

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
    set_mitsuba_variant(variant)
    from src.render.volpath_integrator import register  # defines Mitsuba classes: needs the variant set

    register()
    integrator = mi.load_dict({"type": INTEGRATOR, **dict(ds["integrator"])})
    width, height, reference_spp = int(ds["width"]), int(ds["height"]), int(ds["reference_spp"])
    rng = np.random.default_rng(int(ds["seed"]))  # the RGBE dither
    written = []
    for index, source in enumerate(sources):
        frames = []
        for frame in range(int(ds["frames"])):
            scene = load_volume_frame(source, frame, ds)
            samples = frame_samples(scene, integrator, source.name, ds, frame, spp)
            samples["motion"] = np.zeros_like(samples["position"])
            plan = planned_file(source, ds, frame, reference_spp, "reference")
            from src.render.volume_film import render_volume_buffers

            reference = render_volume_buffers(
                scene, integrator, reference_spp, plan["seeds"], plan["passes"]
            )["color"]
            camera = noisebase_camera(camera_at(source.base, source.seed, frame, ds), width, height)
            frames.append(
                frame_arrays(
                    samples, np.moveaxis(reference, -1, 0), camera, [0, 0], (height, width), rng.random
                )
            )
        if fmt == "training":
            written.append(write_training_sequence(out / f"scene{index:04d}.zip", frames))
        else:
            written += [
                write_test_frame(out / source.name / f"frame{f:04d}.zip", a) for f, a in enumerate(frames)
            ]
    return written
