"""The Noisebase benchmark's scoring protocol (Balint et al. 2023, "Neural Partitioning Pyramids for
Denoising Monte Carlo Renderings", SIGGRAPH; the `noisebase` 1.1.1 package), so that nrbench's numbers
on Noisebase's test sets can sit beside the published ones.

What their scripts do, and what each function here reproduces:

* `noisebase/loaders/torch/test_sample_v1.py::Sequence.save` and `nb_save_reference.py` write every
  frame (method output and reference) as an 8-bit PNG of `(ACES(x) * 255).astype(np.uint8)`, ACES being
  `noisebase/data.py::ACES` (the BakingLab fit of the ACES filmic curve, then clip to [0, 1] and gamma
  1/2.2): truncated, not rounded. -> `srgb8`.
* `noisebase/scripts/nb_compute_metrics.py` reads the PNGs back as float32 in [0, 1] (`np_to_torch`:
  NCHW, / 255) -> `to_unit`, skips the first `warmup` frames of a sequence (16 in test8 and test32)
  -> `score_sequence`, and averages over the remaining frames:
  - `mse` (mean over pixels and channels), `psnr` = 10 log10(1 / mse) per frame, then the mean of the dB
    values (not the dB of the mean MSE);
  - `ssim`, `msssim`: `pytorch_msssim.ssim` / `ms_ssim` (Gaussian window 11, sigma 1.5, K = (0.01,
    0.03), data range 1) on the luminance `srgb_to_lum`: 0.2126 R + 0.7152 G + 0.0722 B of the PNG
    values raised to the power 2.2 -> `luminance`. MS-SSIM's five scales need frames of at least 161
    pixels on their shorter side;
  - `rmae`: mean(|t - r| / (|r| + 0.01)) / 3 (their division by 3, although the mean already runs over
    the channels: kept, it is their number);
  - `flip`: LDR-FLIP (Andersson et al. 2020) as the package's PyTorch port computes it
    (`noisebase/metrics/flip.py::flip`: sRGB -> YCxCz, 67.02 pixels per degree, qc 0.7, qf 0.5, pc 0.4,
    pt 0.95), the mean of the error map; its code is CUDA-only, so `src.metrics.noisebase_flip` carries
    its operations to any device;
  - `tpsnr`, `trmae`: `TemporalMetricAdapter(psnr)` / `(rmae)`: the spatial metric of the frame
    differences (t_i - t_{i-1}, r_i - r_{i-1}) over consecutive pairs after the warm-up, averaged over
    the pairs -> `temporal`;
  - `fvvdp`: FovVideoVDP (Mantiuk et al. 2021) of `pyfvvdp` 1.2.0, display `standard_fhd`, not
    foveated, 30 fps, frames fed one at a time through `noisebase/metrics/fvvdp.py::fvvdp_feeder` (the
    package's streaming version of `fvvdp.predict_video_source`) -> `FovVideoVDPStream`.

Differences, all deliberate:
- Their `psnr` divides a Python float by zero for identical frames (ZeroDivisionError: the script stops);
  ours gives +inf there, and `temporal` gives +inf for a pair whose differences agree exactly.
- Their script moves every frame to 'cuda' (hard-coded); everything here runs on the device it is given
  (CPU by default), and the parity test (tests/test_noisebase_metrics.py) calls their per-frame functions
  on CPU tensors and checks ours equal to 1e-6.
- `pyfvvdp` 1.2.0, the version Noisebase pins and the published FovVideoVDP numbers used, imports
  `numpy.lib.shape_base`, a module numpy 2 renamed (`numpy.lib._shape_base_impl`): `import_pyfvvdp`
  registers the old name for the new module before importing it (the function it needs, `expand_dims`,
  is the same), instead of moving to a later pyfvvdp whose numbers differ.

Every number is recorded with the versions of the packages that computed it (`versions`).
"""

from __future__ import annotations

import importlib.metadata
import sys
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from src.errors import DataError
from src.metrics import noisebase_flip
from src.metrics.own_modules import import_own

#: Frames of each sequence the protocol skips (`warmup` of Noisebase's test8 and test32 configs).
WARMUP = 16
#: Frame rate and display model Noisebase scores FovVideoVDP with (`test_metadata`, `nb_compute_metrics`).
FPS = 30.0
DISPLAY = "standard_fhd"
#: The packages whose code computes the protocol's numbers, recorded beside them.
PACKAGES = ("noisebase", "pytorch-msssim", "pyfvvdp", "torch", "numpy")
#: The per-sequence numbers, in the order of Noisebase's metric files.
METRICS = ("fvvdp", "tpsnr", "trmae", "mse", "psnr", "ssim", "msssim", "flip")
#: The smallest shorter side MS-SSIM's five scales accept: (win_size - 1) * 2 ** 4 + 1.
MSSSIM_MIN_SIDE = 161


def versions() -> dict[str, str]:
    """The installed version of every package the protocol's numbers come from."""
    return {name: importlib.metadata.version(name) for name in PACKAGES}


def import_pyfvvdp():
    """`pyfvvdp.fvvdp`, importable under numpy 2 (module docstring): `pyfvvdp` 1.2.0 does
    `from numpy.lib.shape_base import expand_dims`; numpy 2 keeps that code in
    `numpy.lib._shape_base_impl`, which this registers under the old name first (nothing else changes)."""
    if "numpy.lib.shape_base" not in sys.modules:
        try:
            import numpy.lib.shape_base  # noqa: F401  (numpy < 2: the module is there)
        except ImportError:
            import numpy.lib._shape_base_impl as moved

            sys.modules["numpy.lib.shape_base"] = moved
    package = import_own("pyfvvdp", "pyfvvdp")  # its own `interp`, not pycvvdp's (own_modules.py)
    return package.fvvdp  # the package's metric class (pyfvvdp/__init__.py)


# -- frames ----------------------------------------------------------------------------------------------
def srgb8(linear: np.ndarray) -> np.ndarray:
    """(H, W, 3) linear HDR -> (H, W, 3) uint8 as Noisebase saves a frame: the package's own ACES fit
    (`noisebase/data.py::ACES`: float64, clip to [0, 1], gamma 1/2.2), times 255, truncated."""
    from noisebase.data import ACES

    return (ACES(np.asarray(linear)) * 255).astype(np.uint8)


def to_unit(frame: np.ndarray, device: torch.device | str = "cpu") -> torch.Tensor:
    """(H, W, 3) uint8 -> (1, 3, H, W) float32 in [0, 1] (`nb_compute_metrics.py::np_to_torch`)."""
    return torch.as_tensor(np.asarray(frame)).permute(2, 0, 1)[None].to(device, torch.float32) / 255


def luminance(x: torch.Tensor) -> torch.Tensor:
    """(N, 3, H, W) sRGB-encoded -> (N, 1, H, W) luminance of x ** 2.2 (`srgb_to_lum`)."""
    x = torch.pow(x, 2.2)
    return 0.2126 * x[:, 0:1] + 0.7152 * x[:, 1:2] + 0.0722 * x[:, 2:3]


# -- per-frame metrics, (1, 3, H, W) in [0, 1] (differences of them for the temporal ones) ---------------
def mse(test: torch.Tensor, reference: torch.Tensor) -> float:
    return float(torch.mean((test - reference) ** 2))


def psnr(test: torch.Tensor, reference: torch.Tensor) -> float:
    """10 log10(1 / mse), peak 1; +inf for identical frames (theirs raises ZeroDivisionError)."""
    error = mse(test, reference)
    return float(10 * np.log10(1 / error)) if error > 0 else float("inf")


def rmae(test: torch.Tensor, reference: torch.Tensor) -> float:
    """mean(|t - r| / (|r| + 0.01)) / 3, their division by 3 included (module docstring)."""
    return float(torch.mean(torch.abs(test - reference) / (torch.abs(reference) + 0.01))) / 3


def ssim(test: torch.Tensor, reference: torch.Tensor) -> float:
    """SSIM of the luminances (pytorch_msssim defaults: window 11, sigma 1.5), data range 1."""
    import pytorch_msssim

    return float(pytorch_msssim.ssim(luminance(test), luminance(reference), data_range=1.0))


def msssim(test: torch.Tensor, reference: torch.Tensor) -> float:
    """MS-SSIM of the luminances (five scales: frames of at least 161 pixels a side), data range 1."""
    import pytorch_msssim

    side = min(test.shape[-2:])
    if side < MSSSIM_MIN_SIDE:
        raise DataError(f"MS-SSIM: frames of {side} pixels a side; its five scales need {MSSSIM_MIN_SIDE}")
    return float(pytorch_msssim.ms_ssim(luminance(test), luminance(reference), data_range=1.0))


def flip(test: torch.Tensor, reference: torch.Tensor) -> float:
    """Mean LDR-FLIP error as the package's PyTorch FLIP port computes it (`src.metrics.noisebase_flip`:
    its operations on any device; the package's own code runs on CUDA only)."""
    return noisebase_flip.flip(test, reference)


def temporal(
    metric: Callable[[torch.Tensor, torch.Tensor], float],
    test: Sequence[torch.Tensor],
    reference: Sequence[torch.Tensor],
) -> float:
    """Mean over consecutive pairs of `metric(t_i - t_{i-1}, r_i - r_{i-1})` (`TemporalMetricAdapter`):
    tPSNR with `psnr`, tRMAE with `rmae`. Needs two frames."""
    if len(test) < 2 or len(test) != len(reference):
        raise DataError(
            f"temporal metric: needs two sequences of >= 2 frames, got {len(test)} and {len(reference)}"
        )
    values = [metric(test[i] - test[i - 1], reference[i] - reference[i - 1]) for i in range(1, len(test))]
    return float(sum(values) / len(values))


# -- FovVideoVDP -------------------------------------------------------------------------------------------
class FovVideoVDPStream:
    """FovVideoVDP of a sequence fed one frame pair at a time, as `noisebase/metrics/fvvdp.py`
    (`nb_fvvdp(display_name).video_feeder(H, W, N, fps)` and its `fvvdp_feeder`) computes it: the frames'
    luminance on the display model, the sustained and transient temporal channels from a sliding window
    of `ceil(250 ms * fps)` frames (the first frame replicated before it), each frame's per-band quality
    from `process_block_of_frames`, then `do_pooling_and_jods` over the N frames: JOD, 10 = no visible
    difference."""

    def __init__(
        self,
        height: int,
        width: int,
        frames: int,
        fps: float = FPS,
        display: str = DISPLAY,
        device: torch.device | str = "cpu",
    ) -> None:
        fvvdp = import_pyfvvdp()
        from pyfvvdp.fvvdp import fvvdp_contrast_pyr, fvvdp_lpyr_dec, fvvdp_video_source_dm

        self.vdp = fvvdp(
            display_name=display,
            color_space="sRGB",
            foveated=False,
            heatmap=None,
            quiet=True,
            device=torch.device(device),
            temp_padding="replicate",
            use_checkpoints=False,
        )
        vdp = self.vdp
        pyramid = fvvdp_contrast_pyr if vdp.local_adapt == "gpyr" else fvvdp_lpyr_dec
        vdp.lpyr = pyramid(width, height, vdp.pix_per_deg, vdp.device)
        vdp.filter_len = int(np.ceil(250.0 / (1000.0 / fps)))
        vdp.F, vdp.omega = vdp.get_temporal_filters(fps)
        self.dm = fvvdp_video_source_dm(vdp.display_photometry, vdp.color_space)
        self.height, self.width, self.frames = height, width, frames
        self.window: list[torch.Tensor] = []
        self.quality: torch.Tensor | None = None
        self.fed = 0

    def _luminance(self, frame: torch.Tensor) -> torch.Tensor:
        """(1, 3, H, W) sRGB-encoded in [0, 1] -> (1, 1, 1, H, W) luminance in cd/m^2 on the display."""
        light = self.dm.dm_photometry.forward(frame[:, :, None].to(self.vdp.device))
        weights = self.dm.color_to_luminance
        return light[:, 0:1] * weights[0] + light[:, 1:2] * weights[1] + light[:, 2:3] * weights[2]

    def feed(self, test: torch.Tensor, reference: torch.Tensor) -> None:
        """One frame pair, (1, 3, H, W) in [0, 1]."""
        vdp, shape = self.vdp, (1, 1, self.vdp.filter_len, self.height, self.width)
        frames = (self._luminance(test), self._luminance(reference))
        if self.fed == 0:
            self.window = [f.expand(shape) for f in frames]
        else:
            self.window = [torch.cat((w[:, :, 1:], f), 2) for w, f in zip(self.window, frames, strict=True)]
        # Channels: test-sustained, reference-sustained, test-transient, reference-transient.
        channels = torch.zeros((1, 4, 1, self.height, self.width), device=vdp.device)
        for c in range(2):
            kernel = vdp.F[c].flip(0).view([1, 1, vdp.F[c].shape[0], 1, 1])
            channels[:, 2 * c] = (self.window[0] * kernel).sum(dim=-3, keepdim=True)[:, 0]
            channels[:, 2 * c + 1] = (self.window[1] * kernel).sum(dim=-3, keepdim=True)[:, 0]
        centre = torch.tensor([self.width // 2, self.height // 2])
        block = vdp.process_block_of_frames(
            self.fed, channels, (self.height, self.width, self.frames), 2, centre, None
        )
        if self.quality is None:
            self.quality = torch.zeros((block.shape[0], block.shape[1], self.frames), device=vdp.device)
        self.quality[:, :, self.fed : self.fed + block.shape[2]] = block
        self.fed += 1

    def compute(self) -> float:
        """The sequence's FovVideoVDP in JOD, after all `frames` pairs."""
        if self.fed != self.frames:
            raise DataError(f"FovVideoVDP: fed {self.fed} of the {self.frames} frames it was set up for")
        bands = self.vdp.lpyr.get_freqs()
        return float(self.vdp.do_pooling_and_jods(self.quality, bands[0:-1]).squeeze())


def fovvideovdp(
    test: Sequence[torch.Tensor],
    reference: Sequence[torch.Tensor],
    fps: float = FPS,
    display: str = DISPLAY,
    device: torch.device | str = "cpu",
) -> float:
    """FovVideoVDP (JOD) of two sequences of (1, 3, H, W) frames in [0, 1] (`FovVideoVDPStream`)."""
    if len(test) < 1 or len(test) != len(reference):
        raise DataError(
            f"FovVideoVDP: needs two sequences of one length, got {len(test)} and {len(reference)}"
        )
    height, width = test[0].shape[-2:]
    stream = FovVideoVDPStream(height, width, len(test), fps, display, device)
    for t, r in zip(test, reference, strict=True):
        stream.feed(t, r)
    return stream.compute()


def scored_metrics(height: int, width: int, use_fvvdp: bool = True) -> tuple[str, ...]:
    """The `METRICS` `score_sequence` gives a number for, for frames of `height` x `width`: all but `fvvdp`
    when it is left out and `msssim` under `MSSSIM_MIN_SIDE` pixels a side."""
    left_out = {"fvvdp"} if not use_fvvdp else set()
    if min(height, width) < MSSSIM_MIN_SIDE:
        left_out.add("msssim")
    return tuple(m for m in METRICS if m not in left_out)


# -- a sequence --------------------------------------------------------------------------------------------
def score_sequence(
    test: np.ndarray,
    reference: np.ndarray,
    warmup: int = WARMUP,
    use_fvvdp: bool = True,
    fps: float = FPS,
    device: torch.device | str = "cpu",
) -> dict[str, Any]:
    """Noisebase's numbers for one sequence: `test` and `reference` are (F, H, W, 3) uint8 frames (their
    PNGs; `srgb8` makes them from linear frames). Frames `warmup..F-1` are scored; per-frame metrics are
    means over them, `tpsnr` / `trmae` means over their consecutive pairs, `fvvdp` (JOD) over all of them
    (left out, None, when `use_fvvdp` is false), `msssim` None for frames under 161 pixels a side. Also
    `frames` (the number scored), `warmup` and the package `versions`."""
    test, reference = np.asarray(test), np.asarray(reference)
    if test.shape != reference.shape or test.ndim != 4 or test.shape[-1] != 3 or test.dtype != np.uint8:
        raise DataError(
            f"Noisebase protocol: expected two (F, H, W, 3) uint8 sequences of one shape, got {test.shape} "
            f"{test.dtype} and {reference.shape} {reference.dtype}"
        )
    if not 0 <= warmup <= test.shape[0] - 2:
        raise DataError(
            f"metrics.noisebase.warmup={warmup}: leaves fewer than 2 of the sequence's {test.shape[0]} frames"
        )
    out = [to_unit(f, device) for f in test[warmup:]]
    ref = [to_unit(f, device) for f in reference[warmup:]]
    scored = scored_metrics(*test.shape[1:3], use_fvvdp)
    scores: dict[str, Any] = {
        "fvvdp": fovvideovdp(out, ref, fps, device=device) if "fvvdp" in scored else None,
        "tpsnr": temporal(psnr, out, ref),
        "trmae": temporal(rmae, out, ref),
    }
    for name, metric in (("mse", mse), ("psnr", psnr), ("ssim", ssim), ("msssim", msssim), ("flip", flip)):
        scores[name] = (
            float(np.mean([metric(t, r) for t, r in zip(out, ref, strict=True)])) if name in scored else None
        )
    return {**scores, "frames": len(out), "warmup": warmup, "versions": versions()}
