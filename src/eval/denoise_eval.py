"""Evaluation of a denoiser on the held-out data (`stage=eval`), on every denoising kind of data.

Every held-out item (a scene x noisy spp: a still image, or a whole sequence) is denoised frame by frame
(tiled, `infer_tiled`, so memory stays bounded on large frames; every model, learned or a filter, goes
through the same call, so all are compared on equal terms), timed, and scored against the reference with
`src.metrics.image` (PSNR/SSIM/LPIPS on the tone-mapped image, relMSE/SMAPE/MSE/FLIP on linear HDR),
each also for the noisy input (`noisy_*`). relMSE comes in two conventions: `relmse` (Bako et al. 2017:
mean over pixels and channels) and `relmse_spp` (Davletaliyev 2016, Eq. 3.5: summed over channels, times
spp/2), with `relmse_ratio`, the denoised image's Eq. 3.5 value over the noisy one's (the GP thesis's
fitness term). A row of `per_image.csv` is one item: its frames' metrics averaged; for the kinds of
sequences (`DataKind.temporal`) also its frame count and the temporal-stability metrics of the whole
sequence (`src.metrics.temporal`, all on tone-mapped frames): `temporal` (mean |Δt output - Δt
reference|, the "Flicker" column; its floor is the reference's own noise), `tpsnr` (Noisebase's temporal
PSNR of the frame differences, Balint et al. 2023) and, only where the item holds a second, independently
rendered reference `reference2`, `flicker_unbiased` (the RMS flicker against the noise-free truth,
estimated without bias from the two references; absent, never faked, without one).

With `metrics.protocol=noisebase` every sequence is also scored as the Noisebase benchmark scores it
(`src.metrics.noisebase_protocol`, Balint et al. 2023): the denoised and reference frames made 8-bit as
its PNGs, the first `metrics.noisebase.warmup` frames skipped, then `nb_psnr`, `nb_ssim`, `nb_msssim`,
`nb_flip`, `nb_mse`, `nb_tpsnr`, `nb_trmae` and `nb_fvvdp` (left out with `metrics.noisebase.fvvdp=false`;
`nb_msssim` left out for frames under 161 pixels a side) in the item's row, one JSON per sequence under
`noisebase/` (its numbers beside the versions of the packages that computed them, as Noisebase's own
per-sequence metric files) and the versions as MLflow tags `nrbench.noisebase.<package>`.

With `metrics.cvvdp.enabled=true` every sequence also gets its ColorVideoVDP JOD (Mantiuk et al. 2024;
`src.metrics.cvvdp_metric`: the tone-mapped frames on the SDR display `metrics.cvvdp.display` at
`metrics.cvvdp.fps`): `cvvdp` (denoised) and `noisy_cvvdp` in the item's row, NaN for an item with an
undefined output frame, the `cvvdp` package's version in metrics.json (`cvvdp`) and as the MLflow tag
`nrbench.cvvdp.version`. A video metric: a still-image dataset with it enabled is refused at job start
(`src.schema.run.validate_run`).

Writes `metrics.json` (means overall and per spp), `per_image.csv`, `provenance.json` (resolved config,
git commit, data fingerprint), denoised EXRs, tone-mapped PNGs and comparison strips (a sequence's middle
frame) under `task.eval.out_dir`.
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
from src.io.atomic import atomic_write_json
from src.io.exr import write_exr
from src.io.images import save_comparison_strip, write_png
from src.metrics import cvvdp_metric, noisebase_protocol
from src.metrics.image import image_metrics, relmse_spp, tonemap
from src.metrics.temporal import flicker_unbiased, temporal_error, temporal_psnr
from src.models.denoise.base import Batch, ColorSpace, Denoiser, final_color
from src.models.denoise.models import infer_tiled
from src.models.instantiate import build_method
from src.train.trainer import data_kind

log = logging.getLogger(__name__)

NAN = float("nan")

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
)


@torch.no_grad()
def denoise_tiled(model: Denoiser, batch: Batch, tile: int, space: ColorSpace) -> torch.Tensor:
    """Linear colour (N, 3, H, W) of `batch`, computed in `tile` x `tile` blocks with the model's halo
    (`infer_tiled`: equal to a full-frame pass, memory bounded by the tile), then rebuilt from the
    transformed branches with the data's colour space (a per-pixel operation)."""
    return final_color(infer_tiled(model, batch, tile), batch, space).float()


def _frames_hwc(x: torch.Tensor) -> np.ndarray:
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

    def __init__(self, cfg: DictConfig, tracker) -> None:
        super().__init__(cfg, tracker)
        self.kind = data_kind(cfg)
        self.unit = self.kind.eval_unit
        self.features = self.kind.features(cfg)
        if self.checkpoint is not None:
            self.kind.check_trained_features(self.checkpoint, self.features, str(cfg.task.eval.checkpoint))
        self.space = self.kind.color_space(cfg)
        # A dataset of still images with a video metric is refused at job start (src.schema.run).
        self.protocol = cfg.metrics.get("protocol")
        cvvdp = cfg.metrics.get("cvvdp")
        self.cvvdp = cvvdp if cvvdp is not None and cvvdp.enabled and self.kind.temporal else None
        self.baseline = self._baseline(cfg)

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
            "noisy": _frames_hwc(item["item"]["color"]),
            "denoised": _frames_hwc(output),
            "reference": _frames_hwc(item["item"]["reference"]),
        }
        if self.baseline is not None:
            images["baseline"] = _frames_hwc(self.denoise(self.baseline, item["batch"]))
        return images

    def score(self, item: dict[str, Any], images: dict[str, np.ndarray], seconds: float) -> dict[str, Any]:
        """Per-frame metrics of the denoised and of the noisy frames against the reference, averaged over
        the frames; a sequence's frame count and temporal metrics (module docstring); the runtime per
        frame."""
        denoised, noisy, reference = images["denoised"], images["noisy"], images["reference"]
        m, spp = self.cfg.metrics, int(item["item"]["spp"])
        frames, height, width = reference.shape[:3]
        defined = [bool(np.isfinite(frame).all()) for frame in denoised]
        per_frame = []
        for f in range(frames):
            noisy_row = image_metrics(noisy[f], reference[f], m)
            row = image_metrics(denoised[f], reference[f], m) if defined[f] else dict.fromkeys(noisy_row, NAN)
            row |= {f"noisy_{k}": v for k, v in noisy_row.items()}
            ours = denoised[f] if defined[f] else None
            row |= gp_relmse(ours, noisy[f], reference[f], spp, float(m.relmse_eps))
            if "baseline" in images:  # scored as the run's method is, on the same frame
                base = image_metrics(images["baseline"][f], reference[f], m)
                base |= gp_relmse(images["baseline"][f], noisy[f], reference[f], spp, float(m.relmse_eps))
                row |= {f"baseline_{k}": v for k, v in base.items() if not k.startswith("noisy_")}
            per_frame.append(row)
        # np.mean, not nanmean: an item with an undefined frame has undefined (NaN) metrics
        means = {k: float(np.mean([r[k] for r in per_frame])) for k in per_frame[0]}
        name: dict[str, Any] = {"scene": item["item"]["scene"], "spp": spp}
        undefined = {"undefined": float(frames - sum(defined)) / frames}
        flicker = {}
        if self.kind.temporal:
            name["frames"] = frames
            noisy_scores = self.temporal_scores(item, noisy, reference)
            flicker = (
                self.temporal_scores(item, denoised, reference)
                if all(defined)
                else dict.fromkeys(noisy_scores, NAN)
            )
            flicker |= {f"noisy_{k}": v for k, v in noisy_scores.items()}
        if self.protocol == "noisebase":
            nb_undefined = dict.fromkeys((f"nb_{k}" for k in noisebase_protocol.METRICS), NAN)
            flicker |= self.noisebase_scores(item, denoised, reference) if all(defined) else nb_undefined
        ms_per_frame = seconds * 1e3 / frames
        timing = {"ms_per_image": ms_per_frame, "ms_per_mpixel": ms_per_frame / (height * width / 1e6)}
        return {**name, **means, **flicker, **undefined, **timing}

    def temporal_scores(
        self, item: dict[str, Any], frames: np.ndarray, reference: np.ndarray
    ) -> dict[str, float]:
        """The sequence metrics of one sequence of `frames` against the reference (module docstring):
        the temporal ones, and ColorVideoVDP when enabled."""
        m = self.cfg.metrics
        scores = {
            "temporal": temporal_error(frames, reference, m.tonemap, m.gamma),
            "tpsnr": temporal_psnr(frames, reference, m.tonemap, m.gamma),
        }
        if "reference2" in item["item"]:  # a second, independent render of the reference
            reference2 = _frames_hwc(item["item"]["reference2"])
            scores["flicker_unbiased"] = flicker_unbiased(frames, reference, reference2, m.tonemap, m.gamma)
        if self.cvvdp is not None:
            display, fps = str(self.cvvdp.display), float(self.cvvdp.fps)
            scores["cvvdp"] = cvvdp_metric.cvvdp_jod(
                frames, reference, display, fps, m.tonemap, m.gamma, self.device
            )
        return scores

    def noisebase_scores(
        self, item: dict[str, Any], denoised: np.ndarray, reference: np.ndarray
    ) -> dict[str, float]:
        """The Noisebase protocol's numbers of one sequence (module docstring): written with the package
        versions to `noisebase/<scene>-<spp>spp.json`, returned as `nb_<metric>` (None ones left out)."""
        options = self.cfg.metrics.noisebase
        scores = noisebase_protocol.score_sequence(
            np.stack([noisebase_protocol.srgb8(f) for f in denoised]),
            np.stack([noisebase_protocol.srgb8(f) for f in reference]),
            warmup=int(options.warmup),
            use_fvvdp=bool(options.fvvdp),
            device=self.device,
        )
        name = f"{item['item']['scene']}-{int(item['item']['spp']):05d}spp"
        atomic_write_json(
            self.out_dir / "noisebase" / f"{name}.json", {"model": self.cfg.model.name, **scores}
        )
        return {f"nb_{k}": scores[k] for k in noisebase_protocol.METRICS if scores[k] is not None}

    def header(self) -> dict[str, Any]:
        """metrics.json names the baseline, the Noisebase protocol's settings and package versions, and
        ColorVideoVDP's display, frame rate and package version, when they ran."""
        header = super().header()
        if self.baseline is not None:
            header["baseline"] = self.cfg.task.eval.baseline.get("name")
        if self.cvvdp is not None:
            cvvdp = {"display": str(self.cvvdp.display), "fps": float(self.cvvdp.fps)}
            header["cvvdp"] = cvvdp | {"version": cvvdp_metric.version()}
        if self.protocol != "noisebase":
            return header
        options = self.cfg.metrics.noisebase
        protocol = {
            "warmup": int(options.warmup),
            "fvvdp": bool(options.fvvdp),
            "versions": noisebase_protocol.versions(),
        }
        return {**header, "noisebase_protocol": protocol}

    def logged_tags(self) -> dict[str, str]:
        """The package versions behind the `eval_nb_*` and `eval_cvvdp` metrics, as MLflow tags."""
        tags = {} if self.cvvdp is None else {"nrbench.cvvdp.version": cvvdp_metric.version()}
        if self.protocol != "noisebase":
            return tags
        versions = noisebase_protocol.versions()
        tags |= {f"nrbench.noisebase.{name}": version for name, version in versions.items()}
        return tags | {"nrbench.noisebase.fvvdp": str(bool(self.cfg.metrics.noisebase.fvvdp)).lower()}

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
        per_spp = {
            spp: mean_rows([r for r in rows if r["spp"] == spp]) for spp in sorted({r["spp"] for r in rows})
        }
        return {**super().summarise(rows), "per_spp": per_spp}

    def _log(self, summary: dict[str, Any]) -> None:
        super()._log(summary)
        self.tracker.set_tags(self.logged_tags())

    def logged_metrics(self, summary: dict[str, Any]) -> dict[str, float]:
        metrics = super().logged_metrics(summary)
        for spp, means in summary["per_spp"].items():
            keys = (*SCORES, *(f"{prefix}_{s}" for s in SCORES for prefix in ("noisy", "baseline")))
            metrics |= {f"eval_{k}_spp{spp}": means[k] for k in keys if k in means}  # lpips/flip may be off
        return metrics


def evaluate_denoiser(cfg: DictConfig, tracker) -> dict[str, Any]:
    """Denoise and score every held-out item; returns (and writes) the summary of means."""
    return DenoiseEvaluation(cfg, tracker).run(desc=f"eval {cfg.model.name}")


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
