"""``python -m src.bench volpath``: throughput of the volumetric AOV integrator against Mitsuba's ``volpath``.

One small procedural scene (a floor, a rough metal sphere, an area light, a dim sky and a cube of
heterogeneous smoke: a 16^3 Gaussian density blob in a ``gridvolume`` built from a numpy array) is
rendered at the same resolution, spp, ``max_depth`` and Mitsuba variant by

* ``volpath``: Mitsuba's C++ volumetric path tracer (colour only);
* ``nrbench_volpath`` with ``features=false``: our Python/Dr.Jit integrator, colour only;
* ``nrbench_volpath``: ours with every AOV of ``src.render.volpath_integrator`` and their squares.

Each integrator renders once untimed first (Dr.Jit traces and compiles its kernels then; later renders
reuse them), then ``--repeats`` timed renders, round-robin (a, b, c, a, b, c, ...) so that a load change
on a shared machine affects all alike; the median time of each gives samples per second, and the report
gives ours / volpath (higher is better; 1 = as fast as volpath).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np


def bench_scene_dict(mi, width: int, height: int, grid: int = 16) -> dict:
    """The benchmark scene as a Mitsuba scene dict (needs the variant set)."""
    t = mi.ScalarTransform4f
    z, y, x = np.meshgrid(*(np.linspace(0, 1, grid),) * 3, indexing="ij")
    density = 0.1 + np.exp(-((x - 0.5) ** 2 + (y - 0.4) ** 2 + (z - 0.5) ** 2) * 8)
    density *= 1 + 0.5 * np.sin(12 * x) * np.sin(9 * y) * np.sin(7 * z)  # some structure
    center, half = [0, 0.6, 0], 0.5
    return {
        "type": "scene",
        "sensor": {
            "type": "perspective",
            "fov": 40,
            "to_world": t().look_at(origin=[0, 1, 4], target=[0, 0.5, 0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"}},
            "sampler": {"type": "independent"},
        },
        "floor": {
            "type": "rectangle",
            "to_world": t().rotate([1, 0, 0], -90).scale(3),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.6, 0.5]}},
        },
        "ball": {
            "type": "sphere",
            "center": [0.8, 0.3, -0.3],
            "radius": 0.3,
            "bsdf": {"type": "roughconductor", "alpha": 0.2},
        },
        "light": {
            "type": "rectangle",
            "to_world": t().translate([0, 2.5, 0]).rotate([1, 0, 0], 90).scale(0.5),
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [8, 8, 8]}},
        },
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [0.1, 0.15, 0.2]}},
        "smoke": {
            "type": "cube",
            "to_world": t().translate(center).scale(half),
            "bsdf": {"type": "null"},
            "interior": {
                "type": "heterogeneous",
                "sigma_t": {
                    "type": "gridvolume",
                    "grid": mi.VolumeGrid(density.astype(np.float32)[..., None]),
                    "to_world": t().translate(center).scale(half).translate([-1, -1, -1]).scale(2),
                },
                "scale": 4.0,
                "albedo": {"type": "rgb", "value": [0.9, 0.8, 0.7]},
                "phase": {"type": "hg", "g": 0.3},
            },
        },
    }


def time_renders(mi, scene, integrators: dict, spp: int, repeats: int, seed: int) -> dict[str, float]:
    """Median seconds of ``repeats`` renders per integrator, round-robin, after one untimed render each."""
    for integrator in integrators.values():
        np.asarray(mi.render(scene, integrator=integrator, spp=spp, seed=seed))
    times: dict[str, list[float]] = {name: [] for name in integrators}
    for r in range(repeats):
        for name, integrator in integrators.items():
            start = time.perf_counter()
            np.asarray(mi.render(scene, integrator=integrator, spp=spp, seed=seed + 1 + r))
            times[name].append(time.perf_counter() - start)
    return {name: statistics.median(ts) for name, ts in times.items()}


def run_volpath(args: argparse.Namespace) -> str:
    """Render the benchmark scene with the three integrators; returns the printed report."""
    import drjit as dr

    from src.render.backend import set_mitsuba_variant

    variant = set_mitsuba_variant(args.variant)
    import mitsuba as mi

    from src.render.volpath_integrator import PLUGIN_NAME, register

    register()
    scene = mi.load_dict(bench_scene_dict(mi, args.width, args.height))
    depth = {"max_depth": args.max_depth}
    integrators = {
        "volpath (Mitsuba, colour)": mi.load_dict({"type": "volpath", **depth}),
        f"{PLUGIN_NAME} (colour only)": mi.load_dict({"type": PLUGIN_NAME, "features": False, **depth}),
        f"{PLUGIN_NAME} (all AOVs)": mi.load_dict({"type": PLUGIN_NAME, **depth}),
    }
    seconds = time_renders(mi, scene, integrators, args.spp, args.repeats, args.seed)
    samples = args.width * args.height * args.spp
    base = seconds["volpath (Mitsuba, colour)"]
    lines = [
        f"volpath benchmark: {args.width}x{args.height} at {args.spp} spp ({samples} samples), "
        f"max_depth {args.max_depth}, variant {variant}, {dr.thread_count()} Dr.Jit threads on "
        f"{os.cpu_count()} CPUs; median of {args.repeats} timed renders after 1 untimed (JIT) render each",
        f"{'integrator':34s} {'seconds':>9s} {'Msamples/s':>11s} {'vs volpath':>11s}",
    ]
    for name, s in seconds.items():
        lines.append(f"{name:34s} {s:9.3f} {samples / s / 1e6:11.3f} {base / s:11.2f}")
    lines.append("vs volpath: samples/s relative to Mitsuba's volpath in this run (>= 1: as fast or faster)")
    return "\n".join(lines)
