"""Evaluation of a denoiser on the held-out data (`stage=eval`), on every denoising kind of data.

Every held-out item (a scene x noisy spp: a still image, or a whole sequence) is denoised frame by frame
(tiled, `infer_tiled`, so memory stays bounded on large frames; every model, learned or a filter, goes
through the same call, so all are compared on equal terms), timed, and scored by the run's scorers
(`src/eval/scorers.py`): the per-frame image metrics of the output, the noisy input (`noisy_*`) and the
baseline (`baseline_*`) averaged over the frames, among them relMSE in two conventions (`relmse`, Bako et
al. 2017: mean over pixels and channels; `relmse_spp`, Davletaliyev 2016, Eq. 3.5, with `relmse_ratio`,
the output's over the noisy input's: the GP thesis's fitness term); for the kinds of sequences
(`DataKind.temporal`) the temporal metrics of the whole sequence (`temporal`, the "Flicker" column;
`tpsnr`; `flicker_unbiased` where the item holds a second reference) and, with
`metrics.cvvdp.enabled=true`, ColorVideoVDP (`cvvdp`); with `metrics.protocol=noisebase`, the Noisebase
benchmark's own scoring (`nb_*`, one JSON per sequence under `noisebase/`, package versions as MLflow
tags `nrbench.noisebase.<package>`). A row of `per_image.csv` is one item; a sequence's also holds its
frame count. `undefined` is the item's share of output frames that are not finite.

Writes `metrics.json` (means overall and per spp, and what each scorer records in its header),
`per_image.csv`, `provenance.json` (resolved config, git commit, data fingerprint), denoised EXRs,
tone-mapped PNGs and comparison strips (a sequence's middle frame) under `task.eval.out_dir`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError
from src.eval.common import mean_rows
from src.eval.loop import Evaluation
from src.eval.scorers import frames_hwc, scorers_for
from src.io.exr import write_exr
from src.io.images import save_comparison_strip, write_png
from src.metrics import noisebase_protocol
from src.metrics.image import tonemap
from src.metrics.spp_equivalent import geometric_mean, speedup
from src.models.denoise.base import Batch, ColorSpace, Denoiser, final_color
from src.models.denoise.models import infer_tiled
from src.models.denoise.summary import flops_per_pixel
from src.models.instantiate import build_method

log = logging.getLogger(__name__)

#: Metrics averaged in metrics.json and logged to MLflow as eval_<name> (and eval_noisy_<name>); `temporal`
#: (flicker) and `tpsnr` only where there are sequences, `flicker_unbiased` only where they have a second
#: reference, `cvvdp` only for sequences with `metrics.cvvdp.enabled`.
SCORES = (
    "psnr",
    "ssim",
    "relmse",
    "relmse_spp",
    "relmse_ratio",
    "smape",
    "mse",
    "energy",
    "energy_error",
    "lpips",
    "flip",
    "temporal",
    "tpsnr",
    "flicker_unbiased",
    "cvvdp",
    "undefined",
    *(f"nb_{name}" for name in noisebase_protocol.METRICS),
    "spp_equivalent",
    "spp_equivalent_at_least",
    "speedup",
    "ladder_residual",
    "render_s_per_spp",
)
#: Ratios of sample counts and times, summarised by their geometric mean over the items (NaN ones left out,
#: as `mean_rows` leaves them out and `undefined` counts them); with any "at least" among an item's values,
#: its `<key>_at_least` flag (the share of such items) says the mean is a lower bound too.
GEOMETRIC = {
    "spp_equivalent": "spp_equivalent_at_least",
    "noisy_spp_equivalent": "noisy_spp_equivalent_at_least",
    "speedup": "spp_equivalent_at_least",
}


def geometric_means(rows: list[dict[str, Any]], means: dict[str, float]) -> dict[str, float]:
    """`means` with the `GEOMETRIC` columns' arithmetic means replaced by geometric ones."""
    return means | {key: geometric_mean([r[key] for r in rows]) for key in GEOMETRIC if key in means}


@torch.no_grad()
def denoise_tiled(model: Denoiser, batch: Batch, tile: int, space: ColorSpace) -> torch.Tensor:
    """Linear colour (N, 3, H, W) of `batch`, computed in `tile` x `tile` blocks with the model's halo
    (`infer_tiled`: equal to a full-frame pass, memory bounded by the tile), then rebuilt from the
    transformed branches with the data's colour space (a per-pixel operation)."""
    return final_color(infer_tiled(model, batch, tile), batch, space).float()


class OnDevice(Sequence):
    """The held-out items of `data` with their (F, C, H, W) tensors on the device under "batch" (loaded
    before the timed call)."""

    def __init__(self, data, device: torch.device) -> None:
        self.data, self.device = data, device

    def __len__(self) -> int:
        return len(self.data)

    def __getitem__(self, i: int) -> dict[str, Any]:
        item = self.data[i]
        batch = {k: v.to(self.device) for k, v in item.items() if isinstance(v, torch.Tensor)}
        return {"item": item, "batch": batch}


class DenoiseEvaluation(Evaluation):
    """Every held-out item of `task.eval.split` (scene x noisy spp) of the run's kind of data, denoised
    frame by frame in tiles (module docstring)."""

    artifact_folders = ("strips", "png", "noisebase")

    def __init__(self, cfg: DictConfig, tracker, kind: Any) -> None:
        super().__init__(cfg, tracker)
        self.kind = kind
        self.unit = self.kind.eval_unit
        self.features = self.kind.features(cfg)
        if self.checkpoint is not None:
            self.kind.check_trained_features(self.checkpoint, self.features, str(cfg.task.eval.checkpoint))
        self.space = self.kind.color_space(cfg)
        self.scorers = scorers_for(cfg, self.kind.temporal, self.device, self.out_dir)
        self.baseline = self._baseline(cfg)
        self.flops_per_pixel = self._flops_per_pixel(cfg)

    def _flops_per_pixel(self, cfg: DictConfig) -> float | None:
        """The useful FLOPs of one output pixel, probed with the data's input channels (None: unknown, e.g.
        OIDN): with the timed seconds, the achieved GFLOP/s of the cost card (work redone in tile halos
        lowers it, it adds no FLOPs). A model the probe's random batch cannot run gets None and a warning:
        the cost card is not worth an evaluation."""
        try:  # every dataset config has input_channels (the run schema requires it)
            return flops_per_pixel(self.model, in_channels=int(cfg.dataset.input_channels))["total"]
        except Exception as err:  # a user's model with inputs of its own: no FLOPs, said so
            log.warning("eval: FLOPs per pixel of model=%s unknown (%s); no GFLOP/s", cfg.model.name, err)
            return None

    def _baseline(self, cfg: DictConfig) -> Denoiser | None:
        """`task.eval.baseline` (a filter's model config, e.g. the filter search's constant-sigma
        cross-bilateral filter) built on the device, or None."""
        spec = cfg.task.eval.get("baseline")
        if spec is None:
            return None
        model = build_method(OmegaConf.to_container(spec, resolve=True), section="task.eval.baseline")
        if getattr(model, "learned", True):
            raise ConfigError(
                f"task.eval.baseline: {spec.get('name', spec.get('_target_'))!r} is a learned method; "
                "expected a filter (a baseline is evaluated without a checkpoint)"
            )
        return model.to(self.device).eval()

    def items(self) -> Sequence[dict[str, Any]]:
        return OnDevice(self.kind.held_out(self.cfg, self.features, self.model), self.device)

    @torch.no_grad()
    def denoise(self, model: Denoiser, frames: Batch) -> torch.Tensor:
        """Every frame of an item denoised by `model`, one frame at a time, in tiles."""
        tile, count = int(self.cfg.task.eval.tile), frames["color"].shape[0]
        outputs = [
            denoise_tiled(model, {k: v[f : f + 1] for k, v in frames.items()}, tile, self.space)
            for f in range(count)
        ]
        return torch.cat(outputs)

    def infer(self, item: dict[str, Any]) -> torch.Tensor:
        return self.denoise(self.model, item["batch"])

    def data_dir(self) -> Path:
        return self.kind.raw_dir(self.cfg)

    def untimed(self, item: dict[str, Any], output: torch.Tensor) -> dict[str, np.ndarray]:
        """The noisy, denoised and reference frames, and the baseline's output (not timed) if there is
        one."""
        images = {
            "noisy": frames_hwc(item["item"]["color"]),
            "denoised": frames_hwc(output),
            "reference": frames_hwc(item["item"]["reference"]),
        }
        if self.baseline is not None:
            images["baseline"] = frames_hwc(self.denoise(self.baseline, item["batch"]))
        return images

    def score(self, item: dict[str, Any], images: dict[str, np.ndarray], seconds: float) -> dict[str, Any]:
        """The item's name, each scorer's columns (`src.eval.scorers`: per-frame metrics averaged over the
        frames, a sequence's temporal metrics, ColorVideoVDP, a benchmark protocol), the share of
        undefined output frames and the runtime per frame."""
        frames, height, width = images["reference"].shape[:3]
        defined = [bool(np.isfinite(frame).all()) for frame in images["denoised"]]
        name: dict[str, Any] = {"scene": item["item"]["scene"], "spp": int(item["item"]["spp"])}
        if self.kind.temporal:
            name["frames"] = frames
        scores: dict[str, Any] = {}
        for scorer in self.scorers:
            scores |= scorer.score(item["item"], images, defined)
        undefined = {"undefined": float(frames - sum(defined)) / frames}
        ms_per_frame = seconds * 1e3 / frames
        timing = {"ms_per_image": ms_per_frame, "ms_per_mpixel": ms_per_frame / (height * width / 1e6)}
        if self.flops_per_pixel is not None:
            timing["gflops"] = self.flops_per_pixel * height * width * frames / seconds / 1e9
        if "spp_equivalent" in scores:  # the render time saved, against the timed denoising of a frame
            scores["speedup"] = speedup(
                scores["spp_equivalent"], name["spp"], scores["render_s_per_spp"], seconds / frames
            )
        return {**name, **scores, **undefined, **timing}

    def header(self) -> dict[str, Any]:
        """metrics.json names the baseline, the model's FLOPs per pixel and what each scorer records
        (ColorVideoVDP's display, frame rate and version; the Noisebase protocol's settings and package
        versions), when they ran."""
        header = {**super().header(), "flops_per_pixel": self.flops_per_pixel}
        if self.baseline is not None:
            header["baseline"] = self.cfg.task.eval.baseline.get("name")
        for scorer in self.scorers:
            header |= scorer.header()
        return header

    def logged_tags(self) -> dict[str, str]:
        """The package versions behind the scorers' metrics (`eval_nb_*`, `eval_cvvdp`), as MLflow tags."""
        tags: dict[str, str] = {}
        for scorer in self.scorers:
            tags |= scorer.tags()
        return tags

    def save_outputs(self, item: dict[str, Any], images: dict[str, np.ndarray]) -> None:
        """Every frame's EXR and PNGs (a sequence's named `<scene>-f<FFFF>`), the middle frame's strip."""
        e = self.cfg.task.eval
        frames = images["reference"].shape[0]
        for f in range(frames):
            scene = f"{item['item']['scene']}-f{f:04d}" if self.kind.temporal else item["item"]["scene"]
            options = e if f == frames // 2 else OmegaConf.merge(e, {"strips": False})
            _save_images(
                self.out_dir,
                {**item["item"], "scene": scene},
                {k: v[f] for k, v in images.items()},
                options,
                self.cfg.metrics,
            )

    def summarise(self, rows: list[dict[str, Any]]) -> dict[str, Any]:
        """Means over every item and per noisy spp; the `GEOMETRIC` columns' means are geometric."""
        per_spp = {}
        for spp in sorted({r["spp"] for r in rows}):
            at_spp = [r for r in rows if r["spp"] == spp]
            per_spp[spp] = geometric_means(at_spp, mean_rows(at_spp))
        summary = super().summarise(rows)
        return {**summary, "mean": geometric_means(rows, summary["mean"]), "per_spp": per_spp}

    def _log(self, summary: dict[str, Any]) -> None:
        super()._log(summary)
        self.tracker.set_tags(self.logged_tags())

    def logged_metrics(self, summary: dict[str, Any]) -> dict[str, float]:
        metrics = super().logged_metrics(summary)
        if self.flops_per_pixel is not None:
            metrics["eval_flops_per_pixel"] = float(self.flops_per_pixel)
        for spp, means in summary["per_spp"].items():
            keys = (*SCORES, *(f"{prefix}_{s}" for s in SCORES for prefix in ("noisy", "baseline")))
            metrics |= {f"eval_{k}_spp{spp}": means[k] for k in keys if k in means}  # lpips/flip may be off
        return metrics


def evaluate_denoiser(cfg: DictConfig, tracker, kind: Any) -> dict[str, Any]:
    """Denoise and score every held-out item of the data kind `kind` (the task built it); returns (and
    writes) the summary of means."""
    return DenoiseEvaluation(cfg, tracker, kind).run(desc=f"eval {cfg.model.name}")


def _save_images(
    out_dir: Path, item: dict[str, Any], images: dict[str, np.ndarray], e: DictConfig, m: DictConfig
) -> None:
    """EXR of the denoised image, tone-mapped PNGs of noisy/denoised/reference, the comparison strip."""
    denoised = images["denoised"]
    name = f"{item['scene']}-{int(item['spp']):05d}spp"
    if e.save_exr:
        write_exr(
            out_dir / "images" / f"{name}.exr",
            {"R": denoised[..., 0], "G": denoised[..., 1], "B": denoised[..., 2]},
        )
    # An undefined output's NaN pixels are black in the PNGs (the EXR keeps them NaN).
    ldr = {k: tonemap(np.nan_to_num(v, nan=0.0), m.tonemap, m.gamma) for k, v in images.items()}
    # Tone-mapped PNGs per image: what report grids compare across models (small, unlike EXRs).
    for kind, image in ldr.items():
        write_png(out_dir / "png" / f"{name}-{kind}.png", image)
    if e.strips:
        labels = {
            "noisy": f"noisy {int(item['spp'])} spp",
            "denoised": "denoised",
            "reference": f"reference {int(item['reference_spp'])} spp",
        }
        panels = [(labels[k], ldr[k]) for k in labels]
        save_comparison_strip(out_dir / "strips" / f"{name}.png", panels, int(e.crop_size), int(e.crop_zoom))
