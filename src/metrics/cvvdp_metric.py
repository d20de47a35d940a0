"""ColorVideoVDP (Mantiuk et al. 2024, "ColorVideoVDP: A visual difference predictor for image, video
and display distortions", ACM TOG 43(4)): the perceived quality of a whole denoised sequence against its
reference, in JOD (just-objectionable-difference units: 10 for a sequence indistinguishable from the
reference, lower the more visible the difference; one JOD less means 75% of observers prefer the
reference). It models the display, spatial, temporal and chromatic contrast sensitivity (the castleCSF),
masking, and pools over space, time and channels: what no per-frame metric and no frame-difference
metric sees at once (flicker that is visible on the display, colour shifts, blur in motion).

Computed by the `cvvdp` package itself (import name `pycvvdp`; its version recorded beside every number,
`version`): `pycvvdp.cvvdp(display_name=...).predict(test, reference, dim_order="FHWC",
frames_per_second=...)`, nothing reimplemented. What this module decides, and why:

* Input. The metric takes display-encoded values for an SDR display (sRGB EOTF). nrbench's sequences
  are linear HDR, so both the output and the reference go through `metrics.tonemap` / `metrics.gamma`
  (`src.metrics.image.tonemap`, the values PSNR/SSIM/Flicker see: `clip(x, 0, 1) ** (1/2.2)` by
  default) and are handed over as float32 in [0, 1]. The display then decodes them with its sRGB EOTF
  (close to, not equal to, the 2.2 gamma of the tone map) to cd/m^2.
* Display (`metrics.cvvdp.display`, default `standard_fhd`: the package's 24-inch 1920 x 1080 monitor,
  200 cd/m^2 peak, contrast 1000:1, 250 lux office light, seen from 0.6 m: 37.8 pixels per degree). Only
  the package's SDR display models (display-encoded input, sRGB or gamma EOTF) are accepted
  (`display_names`): an HDR model (PQ, HLG, linear) would read our tone-mapped values as something
  they are not. The frame's own size does not change the display: a 64 x 64 frame is a 64 x 64 patch
  of that monitor.
* Frame rate (`metrics.cvvdp.fps`, default 30): our sequences have no physical frame time (the
  volumetric animations move per frame), and 30 fps is what the Noisebase benchmark gives its sequences
  (`noisebase/loaders/torch/test_sample_v1.py` writes `'fps': 30`) and scores FovVideoVDP at
  (`src.metrics.noisebase_protocol.FPS`). The rate sets the metric's temporal filters, so the same frames
  at another rate score differently.
* Device: the run's (CPU without a GPU); on the CPU the number is deterministic (same frames, same JOD).
  The temporal filters span 250 ms; before the first frame the package repeats it (its default padding).

A frame that is not finite (an undefined output) has no JOD: the caller scores such an item NaN and does
not call this (the metric clamps display values, so NaN would otherwise pass as a number).
"""

from __future__ import annotations

import importlib.metadata
import importlib.util
import json
from functools import cache
from pathlib import Path

import numpy as np
import torch

from src.errors import ConfigError, DataError
from src.metrics.own_modules import import_own, package_dir

#: The package (PyPI name) whose code computes the number, recorded beside it.
PACKAGE = "cvvdp"
#: Defaults of `metrics.cvvdp` (module docstring).
DISPLAY = "standard_fhd"
FPS = 30.0
#: The metric's maximum: a sequence indistinguishable from its reference.
JOD_MAX = 10.0
#: EOTFs of display-encoded SDR input (a number is a gamma); PQ, HLG and linear are HDR.
_SDR_EOTFS = ("sRGB",)


def version() -> str:
    """The installed version of the `cvvdp` package."""
    return importlib.metadata.version(PACKAGE)


def _data_dir() -> Path:
    """The package's `vvdp_data` folder, found without importing the package (it imports torch,
    matplotlib, scipy and huggingface_hub: seconds, paid only by a run that scores with it)."""
    folder = package_dir("pycvvdp")
    if folder is None:
        raise ConfigError("metrics.cvvdp: the cvvdp package is not installed (bash scripts/setup.sh)")
    return folder / "vvdp_data"


@cache
def display_names() -> tuple[str, ...]:
    """The package's display models that take display-encoded SDR input (sRGB or gamma EOTF), in the
    order of its `display_models.json`."""
    data = _data_dir()
    models = json.loads((data / "display_models.json").read_text())
    spaces = json.loads((data / "color_spaces.json").read_text())
    names = []
    for name, model in models.items():
        eotf = str(spaces[model.get("colorspace", "sRGB")]["EOTF"])
        if eotf in _SDR_EOTFS or eotf[:1].isdigit():
            names.append(name)
    return tuple(names)


def check_display(name: str) -> str:
    """`name` if it is one of `display_names`; a one-line ConfigError naming the key otherwise."""
    if name not in display_names():
        raise ConfigError(
            f"metrics.cvvdp.display={name!r}: expected an SDR display model of cvvdp {version()}, one of "
            f"{', '.join(display_names())}"
        )
    return name


def display_encoded(frames: np.ndarray, method: str, gamma: float) -> np.ndarray:
    """(F, H, W, 3) linear frames -> float32 display values in [0, 1] (`tonemap`), a frame at a time (no
    float64 copy of a whole sequence); a one-line DataError for a NaN/Inf value."""
    frames = np.asarray(frames)
    if frames.ndim != 4 or frames.shape[-1] != 3:
        raise DataError(f"cvvdp: expected frames of shape (F, H, W, 3), got {frames.shape}")
    if not np.isfinite(frames).all():
        raise DataError(f"cvvdp: the frames have {np.count_nonzero(~np.isfinite(frames))} NaN/Inf values")
    # Imported here: the job-start check of metrics.cvvdp.display imports this module, and
    # src.metrics.image brings LPIPS and torchvision (about 1 s) that the check does not need.
    from src.metrics.image import tonemap

    out = np.empty(frames.shape, dtype=np.float32)
    for f, frame in enumerate(frames):
        out[f] = tonemap(frame, method, gamma)
    return out


def cvvdp_jod(
    frames: np.ndarray,
    reference: np.ndarray,
    display: str = DISPLAY,
    fps: float = FPS,
    method: str = "clip_gamma",
    gamma: float = 2.2,
    device: torch.device | str = "cpu",
) -> float:
    """ColorVideoVDP JOD of the linear HDR sequence `frames` (F, H, W, 3) against `reference`, both tone
    mapped (`method`, `gamma`) and shown on `display` at `fps` (module docstring); higher is better,
    `JOD_MAX` for a copy of the reference."""
    pycvvdp = import_own("pycvvdp", "pycvvdp")  # lazy: module docstring (`_data_dir`); own `interp`

    check_display(display)
    if np.shape(frames) != np.shape(reference):
        shapes = f"denoised {np.shape(frames)} vs reference {np.shape(reference)}"
        raise DataError(f"cvvdp: shapes differ, {shapes}")
    if not fps > 0:
        raise ConfigError(f"metrics.cvvdp.fps={fps!r}: expected a positive number")
    test, ref = display_encoded(frames, method, gamma), display_encoded(reference, method, gamma)
    metric = pycvvdp.cvvdp(display_name=display, device=torch.device(device), quiet=True)
    jod, _ = metric.predict(test, ref, dim_order="FHWC", frames_per_second=float(fps))
    return float(jod)
