"""What the denoising evaluation scores an item with: one scorer object per kind of score, iterated by
`DenoiseEvaluation` (src/eval/denoise_eval.py) in the order `scorers_for` builds them.

An item is a held-out scene at one sample count: a still image, or a whole sequence. A scorer gets the
item's denoised, noisy and reference frames ((F, H, W, 3) linear HDR; `baseline` too when the run scores
one) and which denoised frames are defined (finite), and returns the columns it adds to the item's row of
`per_image.csv`. A scorer also says what metrics.json's header records of it and which MLflow tags name
the packages behind its numbers.

- `FrameScores`: the per-frame image metrics (`src.metrics.image`: PSNR, SSIM, LPIPS on the tone-mapped
  frame, relMSE, SMAPE, MSE, FLIP, energy on linear HDR) and the GP thesis's relMSE (Eq. 3.5) and its
  ratio, of the output, the noisy input (`noisy_*`) and the baseline (`baseline_*`), averaged over the
  frames; every item.
- `SequenceScores`: the temporal metrics of the whole sequence (`src.metrics.temporal`): the flicker
  against the reference (`temporal`), Noisebase's temporal PSNR (`tpsnr`) and, where the item has a
  second reference, the flicker against the truth (`flicker_unbiased`); kinds of sequences only.
- `ColorVideoVdp`: ColorVideoVDP's JOD of the whole sequence (`cvvdp`; `metrics.cvvdp.enabled`).
- `SppEquivalentScores`: the samples per pixel a plain render needs to reach the output's (and the noisy
  input's) error, from the scene's ladder of plain renders (`spp_equivalent`, `noisy_spp_equivalent`, with
  their "at least" flags, the fit's residual and limit, the render seconds per spp;
  `metrics.spp_equivalent.enabled` and a rendered ladder).
- `NoisebaseProtocol`: the Noisebase benchmark's own scoring (`nb_*`; `metrics.protocol=noisebase`).

Another benchmark protocol is one class with these four methods and its name in `PROTOCOLS`, chosen by
`metrics.protocol=<name>`. An output frame that is undefined (a GP expression's NaN weights) makes the
output's scores of its item NaN, never dropped: the ledger counts them as the arm's worst.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig

from src.data.ladder import MANIFEST_DIR, ladder_counts, read_ladder
from src.io.atomic import atomic_write_json
from src.metrics import cvvdp_metric, noisebase_protocol
from src.metrics.image import image_metrics, mse, relmse, relmse_spp
from src.metrics.spp_equivalent import (
    MonteCarloFit,
    fit_monte_carlo,
    measurable_limit,
    seconds_per_spp,
    spp_equivalent,
)
from src.metrics.temporal import flicker_unbiased, temporal_error, temporal_psnr
from src.provenance import data_fingerprint

log = logging.getLogger(__name__)
NAN = float("nan")
Frames = Mapping[str, np.ndarray]


def frames_hwc(x: torch.Tensor) -> np.ndarray:
    """(F, 3, H, W) -> (F, H, W, 3) float32 numpy."""
    return x.permute(0, 2, 3, 1).cpu().numpy().astype(np.float32)


def gp_relmse(
    denoised: np.ndarray | None, noisy: np.ndarray, reference: np.ndarray, spp: int, eps: float
) -> dict[str, float]:
    """The GP thesis's relMSE (Davletaliyev 2016, Eq. 3.5) of the denoised and the noisy image, and their
    ratio: that image's term of the thesis's fitness (its scenes' ratios averaged). `denoised` None (an
    undefined output): its relMSE and the ratio are NaN."""
    noisy_value = relmse_spp(noisy, reference, spp, eps)
    ours = NAN if denoised is None else relmse_spp(denoised, reference, spp, eps)
    ratio = ours / noisy_value if noisy_value > 0 else NAN
    return {"relmse_spp": ours, "noisy_relmse_spp": noisy_value, "relmse_ratio": ratio}


class Scorer:
    """One kind of score of an item (module docstring). The defaults add nothing to the header or tags."""

    def score(self, item: Mapping[str, Any], images: Frames, defined: list[bool]) -> dict[str, float]:
        raise NotImplementedError

    def header(self) -> dict[str, Any]:
        return {}

    def tags(self) -> dict[str, str]:
        return {}


class FrameScores(Scorer):
    """Per-frame image metrics of the output, the noisy input and the baseline, means over the frames."""

    def __init__(self, metrics: DictConfig) -> None:
        self.metrics = metrics

    def score(self, item: Mapping[str, Any], images: Frames, defined: list[bool]) -> dict[str, float]:
        denoised, noisy, reference = images["denoised"], images["noisy"], images["reference"]
        m, spp, eps = self.metrics, int(item["spp"]), float(self.metrics.relmse_eps)
        per_frame = []
        for f in range(reference.shape[0]):
            noisy_row = image_metrics(noisy[f], reference[f], m)
            row = image_metrics(denoised[f], reference[f], m) if defined[f] else dict.fromkeys(noisy_row, NAN)
            row |= {f"noisy_{k}": v for k, v in noisy_row.items()}
            row |= gp_relmse(denoised[f] if defined[f] else None, noisy[f], reference[f], spp, eps)
            if "baseline" in images:  # scored as the run's method is, on the same frame
                base = image_metrics(images["baseline"][f], reference[f], m)
                base |= gp_relmse(images["baseline"][f], noisy[f], reference[f], spp, eps)
                row |= {f"baseline_{k}": v for k, v in base.items() if not k.startswith("noisy_")}
            per_frame.append(row)
        # np.mean, not nanmean: an item with an undefined frame has undefined (NaN) metrics
        return {k: float(np.mean([r[k] for r in per_frame])) for k in per_frame[0]}


class _WholeSequence(Scorer):
    """A score of a whole sequence, of the output (NaN when a frame is undefined) and of the noisy input."""

    def of(self, item: Mapping[str, Any], frames: np.ndarray, reference: np.ndarray) -> dict[str, float]:
        raise NotImplementedError

    def score(self, item: Mapping[str, Any], images: Frames, defined: list[bool]) -> dict[str, float]:
        noisy = self.of(item, images["noisy"], images["reference"])
        ours = (
            self.of(item, images["denoised"], images["reference"])
            if all(defined)
            else dict.fromkeys(noisy, NAN)
        )
        return ours | {f"noisy_{k}": v for k, v in noisy.items()}


class SequenceScores(_WholeSequence):
    """The temporal metrics of a sequence (module docstring), on the tone-mapped frames."""

    def __init__(self, metrics: DictConfig) -> None:
        self.tonemap, self.gamma = metrics.tonemap, metrics.gamma

    def of(self, item: Mapping[str, Any], frames: np.ndarray, reference: np.ndarray) -> dict[str, float]:
        scores = {
            "temporal": temporal_error(frames, reference, self.tonemap, self.gamma),
            "tpsnr": temporal_psnr(frames, reference, self.tonemap, self.gamma),
        }
        if "reference2" in item:  # a second, independent render of the reference
            reference2 = frames_hwc(item["reference2"])
            scores["flicker_unbiased"] = flicker_unbiased(
                frames, reference, reference2, self.tonemap, self.gamma
            )
        return scores


class ColorVideoVdp(_WholeSequence):
    """ColorVideoVDP's JOD of a sequence: the tone-mapped frames on `metrics.cvvdp.display` at its fps."""

    def __init__(self, metrics: DictConfig, device: torch.device) -> None:
        self.display, self.fps = str(metrics.cvvdp.display), float(metrics.cvvdp.fps)
        self.tonemap, self.gamma, self.device = metrics.tonemap, metrics.gamma, device

    def of(self, item: Mapping[str, Any], frames: np.ndarray, reference: np.ndarray) -> dict[str, float]:
        jod = cvvdp_metric.cvvdp_jod(
            frames, reference, self.display, self.fps, self.tonemap, self.gamma, self.device
        )
        return {"cvvdp": jod}

    def header(self) -> dict[str, Any]:
        return {"cvvdp": {"display": self.display, "fps": self.fps, "version": cvvdp_metric.version()}}

    def tags(self) -> dict[str, str]:
        return {"nrbench.cvvdp.version": cvvdp_metric.version()}


class NoisebaseProtocol(Scorer):
    """The Noisebase benchmark's scoring of a sequence (Balint et al. 2023; `src.metrics.noisebase_protocol`):
    the frames made 8-bit as its PNGs, the first `metrics.noisebase.warmup` skipped, `nb_<metric>` (None
    ones left out); one JSON per sequence under `<out_dir>/noisebase/`, beside the package versions."""

    def __init__(self, metrics: DictConfig, device: torch.device, out_dir: Path, model: str) -> None:
        options = metrics.noisebase
        self.warmup, self.fvvdp = int(options.warmup), bool(options.fvvdp)
        self.device, self.out_dir, self.model = device, out_dir, model

    def score(self, item: Mapping[str, Any], images: Frames, defined: list[bool]) -> dict[str, float]:
        if not all(defined):  # NaN for each number a defined sequence of this size would have
            height, width = images["reference"].shape[1:3]
            scored = noisebase_protocol.scored_metrics(height, width, self.fvvdp)
            return dict.fromkeys((f"nb_{k}" for k in scored), NAN)
        scores = noisebase_protocol.score_sequence(
            np.stack([noisebase_protocol.srgb8(f) for f in images["denoised"]]),
            np.stack([noisebase_protocol.srgb8(f) for f in images["reference"]]),
            warmup=self.warmup,
            use_fvvdp=self.fvvdp,
            device=self.device,
        )
        name = f"{item['scene']}-{int(item['spp']):05d}spp"
        atomic_write_json(self.out_dir / "noisebase" / f"{name}.json", {"model": self.model, **scores})
        return {f"nb_{k}": scores[k] for k in noisebase_protocol.METRICS if scores[k] is not None}

    def header(self) -> dict[str, Any]:
        versions = noisebase_protocol.versions()
        return {"noisebase_protocol": {"warmup": self.warmup, "fvvdp": self.fvvdp, "versions": versions}}

    def tags(self) -> dict[str, str]:
        tags = {f"nrbench.noisebase.{name}": v for name, v in noisebase_protocol.versions().items()}
        return tags | {"nrbench.noisebase.fvvdp": str(self.fvvdp).lower()}


class SppEquivalentScores(Scorer):
    """The samples a denoiser saves (`src.metrics.spp_equivalent`): per item, Eq. (1) fitted to its scene's
    ladder of plain renders (`src.data.ladder`; every frame of a sequence, errors averaged over the frames)
    against the item's own reference, then the output's and the noisy input's equivalent counts (Eq. (2);
    "at least" past what the ladder and the reference's noise can measure), the fit's residual and limit,
    and the render seconds per sample per frame of the scene. The error is `metrics.spp_equivalent.metric`:
    relMSE with the relMSE column's eps and crop, or MSE. A fit is made once per scene."""

    def __init__(self, metrics: DictConfig, ladder_dir: Path, counts: list[int], temporal: bool) -> None:
        options = metrics.spp_equivalent
        self.metric, self.margin = str(options.metric), float(options.margin)
        self.eps, self.crop = float(metrics.relmse_eps), int(metrics.relmse_crop)
        self.ladder_dir, self.counts, self.temporal = ladder_dir, counts, temporal
        self.fits: dict[str, tuple[MonteCarloFit, float]] = {}

    def error(self, frames: np.ndarray, reference: np.ndarray) -> float:
        """The metric's mean over the frames (linear in 1 / spp, as Eq. (1) needs)."""
        if self.metric == "mse":
            return float(np.mean([mse(f, r) for f, r in zip(frames, reference, strict=True)]))
        return float(
            np.mean([relmse(f, r, self.eps, self.crop) for f, r in zip(frames, reference, strict=True)])
        )

    def fit(self, scene: str, reference: np.ndarray) -> tuple[MonteCarloFit, float]:
        """Eq. (1) of `scene`'s ladder against `reference`, and its render seconds per spp (cached)."""
        if scene not in self.fits:
            frames = reference.shape[0] if self.temporal else None
            ladder = read_ladder(self.ladder_dir, scene, self.counts, frames)
            errors = [self.error(ladder.frames[n], reference) for n in self.counts]
            seconds = seconds_per_spp(self.counts, [ladder.seconds[n] for n in self.counts])
            self.fits[scene] = (fit_monte_carlo(self.counts, errors), seconds)
        return self.fits[scene]

    def score(self, item: Mapping[str, Any], images: Frames, defined: list[bool]) -> dict[str, float]:
        reference = images["reference"]
        fit, seconds = self.fit(str(item["scene"]), reference)
        noisy = spp_equivalent(fit, self.error(images["noisy"], reference), self.margin)
        ours = (
            spp_equivalent(fit, self.error(images["denoised"], reference), self.margin)
            if all(defined)
            else None
        )
        return {
            "spp_equivalent": NAN if ours is None else ours.value,
            "spp_equivalent_at_least": NAN if ours is None else float(ours.at_least),
            "noisy_spp_equivalent": noisy.value,
            "noisy_spp_equivalent_at_least": float(noisy.at_least),
            "ladder_residual": fit.residual,
            "ladder_limit": measurable_limit(fit, self.margin),
            "render_s_per_spp": seconds,
        }

    def header(self) -> dict[str, Any]:
        return {
            "spp_equivalent": {
                "metric": self.metric,
                "margin": self.margin,
                "ladder_spp": self.counts,
                "ladder_fingerprint": data_fingerprint(self.ladder_dir),
            }
        }


def spp_equivalent_scorer(cfg: DictConfig, temporal: bool) -> Scorer | None:
    """The run's `SppEquivalentScores`, or None (logged) when it is off, the dataset has no ladder
    (`dataset.ladder_spp` empty or absent: a user's EXRs) or no ladder was ever rendered in
    `paths.ladder` (a user's KPCN EXRs read with `paths.raw=`)."""
    options = cfg.metrics.get("spp_equivalent")
    if options is None or not options.enabled:
        return None
    counts = ladder_counts(cfg.dataset) if "reference_spp" in cfg.dataset else []
    ladder_dir = Path(cfg.paths.ladder) if cfg.paths.get("ladder") else None
    if not counts or ladder_dir is None or not (ladder_dir / MANIFEST_DIR).is_dir():
        where = "dataset.ladder_spp is empty" if not counts else f"no ladder was rendered in {ladder_dir}"
        log.info("eval: no spp-equivalent (%s; stage=render makes the ladder of a rendered dataset)", where)
        return None
    return SppEquivalentScores(cfg.metrics, ladder_dir, counts, temporal)


#: `metrics.protocol` -> the benchmark protocol's scorer class (built with the metrics config, the device,
#: the evaluation's output folder and the model's name).
PROTOCOLS: dict[str, type[Scorer]] = {"noisebase": NoisebaseProtocol}


def scorers_for(cfg: DictConfig, temporal: bool, device: torch.device, out_dir: Path) -> list[Scorer]:
    """The scorers of a run, in the order their columns come in a row: the per-frame metrics always; the
    sequence metrics and ColorVideoVDP (`metrics.cvvdp.enabled`) for kinds of sequences (`temporal`); the
    spp-equivalent where there is a ladder (`spp_equivalent_scorer`); the benchmark protocol
    `metrics.protocol` names. A still-image dataset with a video metric is refused at
    job start (`src.schema.run.validate_run`)."""
    m = cfg.metrics
    scorers: list[Scorer] = [FrameScores(m)]
    if temporal:
        scorers.append(SequenceScores(m))
        cvvdp = m.get("cvvdp")
        if cvvdp is not None and cvvdp.enabled:
            scorers.append(ColorVideoVdp(m, device))
    equivalent = spp_equivalent_scorer(cfg, temporal)
    if equivalent is not None:
        scorers.append(equivalent)
    protocol = m.get("protocol")
    if protocol is not None:
        scorers.append(PROTOCOLS[protocol](m, device, out_dir, str(cfg.model.name)))
    return scorers
