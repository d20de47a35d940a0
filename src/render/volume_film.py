"""The film of the volumetric path tracer (``nrbench_volpath``, ``src.render.volpath_integrator``): which
film channel holds what, and the rendered films turned back into buffers and their variances.

Layout: the film's RGB is ``color``; the AOVs follow in ``VOLUME_BUFFERS`` order (``src.data.volume_aovs``)
and then the per-sample square of every buffer in ``MOMENT_BUFFERS`` (``color`` first). The integrator
writes its AOVs in that order (``film_aovs``, named by ``volume_channel_names``) and ``split_film`` reads
them back, so the layout is written down once, here. ``render_volume_buffers`` renders a scene in passes,
averages the passes' films (``src.render.moments.MomentAccumulator``) and returns each buffer's per-pixel
mean and the variance of that mean; it is to the volumetric renders what
``src.render.render_dataset.render_buffers`` is to the still images.
"""

from __future__ import annotations

from collections.abc import Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from src.data.volume_aovs import CHANNEL_COUNT, MOMENT_BUFFERS, VOLUME_BUFFERS
from src.render.moments import MomentAccumulator, variance_of_mean


def volume_channel_names() -> list[str]:
    """AOV channel names in the order the integrator's ``sample`` returns them (``film_aovs``): buffers,
    then squares."""
    names = []
    for buf, n in VOLUME_BUFFERS.items():
        names += [f"{buf}.{i}" for i in range(n)]
    for buf in MOMENT_BUFFERS:
        names += [f"{buf}_sq.{i}" for i in range(CHANNEL_COUNT[buf])]
    return names


def _channels(x, n: int) -> list:
    return [x[i] for i in range(n)] if n > 1 else [x]


def film_aovs(values: dict) -> list:
    """The integrator's per-sample AOV list from its ``values`` (buffer -> Dr.Jit value): the channels in
    ``volume_channel_names`` order, the buffers, then the squares of ``MOMENT_BUFFERS``."""
    aovs = []
    for buf, n in VOLUME_BUFFERS.items():
        aovs += _channels(values[buf], n)
    for buf in MOMENT_BUFFERS:
        aovs += [dr.square(c) for c in _channels(values[buf], CHANNEL_COUNT[buf])]
    return aovs


def split_film(img: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """(mean, second moment) per buffer from a film image laid out as ``volume_channel_names``."""
    out, start = {}, 0
    offsets = {}
    for buf, n in CHANNEL_COUNT.items():
        offsets[buf] = (start, start + n)
        start += n
    for buf, n in CHANNEL_COUNT.items():
        a, b = offsets[buf]
        out[buf] = (img[..., a:b], img[..., start : start + n])
        start += n
    if start != img.shape[-1]:
        raise ValueError(f"film has {img.shape[-1]} channels, the volumetric layout {start}")
    return out


def render_volume_buffers(
    scene, integrator, spp: int, seeds: Sequence[int] = (0,), passes: Sequence[int] | None = None, sensor=None
) -> dict[str, np.ndarray]:
    """Render ``spp`` samples (in ``passes``, one seed each) with a ``nrbench_volpath`` integrator.

    Returns each buffer's per-pixel mean (H, W, C) float32 and ``<buffer>Variance`` (H, W, 1), the
    variance of that mean averaged over channels (``src.render.moments``; left out at 1 spp)."""
    passes = [spp] if passes is None else list(passes)
    if sum(passes) != spp:
        raise ValueError(f"passes {passes} do not sum to spp={spp}")
    acc = MomentAccumulator()
    sensor = scene.sensors()[0] if sensor is None else sensor
    for seed, n in zip(seeds, passes, strict=True):
        acc.add(np.asarray(mi.render(scene, sensor=sensor, integrator=integrator, spp=n, seed=seed)), n)
    buffers = {}
    for buf, (mean, second) in split_film(acc.mean()).items():
        buffers[buf] = mean.astype(np.float32)
        if spp >= 2:
            buffers[f"{buf}Variance"] = variance_of_mean(mean, second, spp).astype(np.float32)
    return buffers
