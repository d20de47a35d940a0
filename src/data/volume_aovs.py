"""The buffers the volumetric path tracer (``src.render.volpath_integrator``) writes, declared without
importing Mitsuba: the integrator's film layout and the volumetric EXR layout (``src.data.volume_buffers``)
are both derived from these, so a buffer added here reaches the files without a second list to update.
A data layout, so it lives in ``src/data``: the renderer imports it, the data modules never import the
renderer.
"""

from __future__ import annotations

#: AOV buffers after the film's RGB ``color``, in output order, with their channel counts.
VOLUME_BUFFERS: dict[str, int] = {
    "surface": 3,
    "volume": 3,
    "volume_single": 3,
    "volume_multi": 3,
    "albedo": 3,
    "normal": 3,
    "depth": 1,
    "visibility": 1,
    "position": 3,
    "transmittance": 3,
    "optical_thickness": 3,
    "scatter_depth": 1,
    "scatter_position": 3,
    "scatter_media_distance": 1,
    "sigma_t": 3,
    "sigma_s": 3,
    "scatter_albedo": 3,
    "scattered": 1,
    "volume_events": 1,
}
#: Every buffer with its channel count, ``color`` first (the film's RGB).
CHANNEL_COUNT: dict[str, int] = {"color": 3, **VOLUME_BUFFERS}
#: Buffers whose per-sample square is written too, in output order after the AOVs.
MOMENT_BUFFERS: tuple[str, ...] = tuple(CHANNEL_COUNT)
