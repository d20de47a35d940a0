"""A kind of data from outside `src/`, as a user would write one (docs/extending.md):
small analytic image sequences. Each scene is a few frames of drifting sinusoids per colour channel; a
noisy render at s spp adds Gaussian noise of std `noise / sqrt(s)`, seeded per (scene, spp). The kind
owns its render (the clean and noisy frames into `paths.raw`), its preprocessing (k-frame training
samples and whole held-out sequences into `paths.prepared`), the datasets the one denoising trainer and
evaluation read, its colour space (one `radiance` branch, linear) and its loss terms (reconstruction plus
the temporal term). Its options are its `dataset:` group (`tests/conf/dataset/toy_sequence.yaml`), which
the job passes to its constructor and its `schema` checks there (`self.dataset` holds them); the tests
train and evaluate a toy denoiser and DPCN on it through a multirun and the report, without any edit
under `src/`."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import DictConfig
from torch.utils.data import IterableDataset

from src.data.color_spaces import RadianceTransform
from src.io.atomic import atomic_directory, atomic_write_json
from src.kinds.denoising import DenoisingKind
from src.objectives.losses import get_loss
from src.objectives.terms import TemporalLosses
from src.schema.dataset import DenoisingData
from src.schema.types import PositiveFloat, PositiveInt

SPLITS = ("train", "val", "test")


def clean_frames(scene: int, frames: int, height: int, width: int) -> np.ndarray:
    """(F, 3, H, W) radiance in [0.1, 0.9]: per channel a sinusoid whose phase drifts from frame to frame."""
    t = np.arange(frames)[:, None, None, None]
    c = np.arange(3)[None, :, None, None]
    y = np.linspace(0, 1, height)[None, None, :, None]
    x = np.linspace(0, 1, width)[None, None, None, :]
    phase = 2 * math.pi * (x * (1 + scene % 3) + 0.5 * y + 0.1 * t * (1 + c)) + scene
    return (0.5 + 0.4 * np.sin(phase) * np.cos(math.pi * y * (c + 1))).astype(np.float32)


def split_of(scene: int, scenes: int) -> str:
    """Half the scenes train, a quarter val, the rest test."""
    return "train" if scene < scenes // 2 else "val" if scene < 3 * scenes // 4 else "test"


def sequence_item(clean: np.ndarray, noisy: np.ndarray, variance: float) -> dict[str, torch.Tensor]:
    """The batch contract's tensors of one sequence, (F, C, H, W)."""
    noisy_t, clean_t = torch.from_numpy(noisy), torch.from_numpy(clean)
    frames, _, h, w = noisy_t.shape
    const = lambda value, c=3: torch.full((frames, c, h, w), value)  # noqa: E731
    return {
        "radiance_in": torch.cat([noisy_t, const(variance, 1)], dim=1),
        "radiance_t": noisy_t,
        "radiance_target": clean_t,
        "color": noisy_t,
        "reference": clean_t,
        "albedo": const(0.5),
        "normal": torch.cat([const(0.0, 2), const(1.0, 1)], dim=1),
        "depth": const(0.5, 1),
        "motion": const(0.0, 2),
    }


class ToySamples(IterableDataset):
    """The k-frame samples of one split, reshuffled per (seed, epoch)."""

    def __init__(self, path: Path, seed: int, shuffle: bool) -> None:
        super().__init__()
        self.samples = torch.load(path, weights_only=True)
        self.seed, self.shuffle, self.epoch = seed, shuffle, 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.samples["color"])

    def __iter__(self):
        order = np.random.default_rng([self.seed, self.epoch]).permutation(len(self))
        for i in order if self.shuffle else range(len(self)):
            yield {k: v[i] for k, v in self.samples.items()}


class ToyData(DenoisingData):
    """The toy kind's `dataset:` keys: a value outside these is one line naming the key at job start."""

    name: str
    experiment_suffix: str
    scenes: PositiveInt
    frames: PositiveInt
    sequence_frames: PositiveInt
    width: PositiveInt
    height: PositiveInt
    noisy_spp: list[PositiveInt]
    noise: PositiveFloat
    temporal_weight: float
    seed: int


class ToySequences(DenoisingKind):
    """Analytic sequences with Gaussian noise (module docstring)."""

    schema = ToyData
    describes = "toy analytic sequences"
    eval_unit = "seq"
    temporal = True

    def render(self, cfg: DictConfig) -> dict[str, Any]:
        ds, raw = self.dataset, self.raw_dir(cfg)
        with atomic_directory(raw) as tmp:
            for scene in range(ds["scenes"]):
                clean = clean_frames(scene, ds["frames"], ds["height"], ds["width"])
                noisy = {}
                for spp in ds["noisy_spp"]:
                    rng = np.random.default_rng([ds["seed"], scene, spp])
                    noise = rng.normal(0.0, ds["noise"] / math.sqrt(spp), clean.shape)
                    noisy[str(spp)] = torch.from_numpy((clean + noise).astype(np.float32))
                torch.save({"clean": torch.from_numpy(clean), "noisy": noisy}, tmp / f"scene{scene:03d}.pt")
        print(f"render: {ds['scenes']} toy sequences -> {raw}")
        return {"scenes": ds["scenes"]}

    def preprocess(self, cfg: DictConfig) -> dict[str, Any]:
        ds, out, k = self.dataset, Path(cfg.paths.prepared), self.dataset["sequence_frames"]
        samples: dict[str, list[dict[str, torch.Tensor]]] = {"train": [], "val": []}
        full: dict[str, list[dict[str, Any]]] = {"val": [], "test": []}
        for scene in range(ds["scenes"]):
            data = torch.load(self.raw_dir(cfg) / f"scene{scene:03d}.pt", weights_only=True)
            split = split_of(scene, ds["scenes"])
            for spp, noisy in data["noisy"].items():
                item = sequence_item(data["clean"].numpy(), noisy.numpy(), ds["noise"] ** 2 / int(spp))
                if split in samples:
                    for start in range(ds["frames"] - k + 1):
                        samples[split].append({key: v[start : start + k] for key, v in item.items()})
                if split in full:
                    full[split].append({"scene": f"scene{scene:03d}", "spp": int(spp), **item})
        with atomic_directory(out) as tmp:
            for split, items in samples.items():
                (tmp / "patches" / split).mkdir(parents=True)
                stacked = {key: torch.stack([s[key] for s in items]) for key in items[0]}
                torch.save(stacked, tmp / "patches" / split / "samples.pt")
                atomic_write_json(tmp / "patches" / split / "index.json", {"samples": len(items)})
            for split, items in full.items():
                (tmp / "full" / split).mkdir(parents=True)
                torch.save(items, tmp / "full" / split / "sequences.pt")
                atomic_write_json(tmp / "full" / split / "index.json", {"sequences": len(items)})
        summary = {
            "samples": {s: len(v) for s, v in samples.items()},
            "full": {s: len(v) for s, v in full.items()},
        }
        print(f"preprocess: toy sequences {json.dumps(summary)} -> {out}")
        return summary

    def features(self, cfg: DictConfig) -> None:
        return None  # one fixed input group

    def check_trained_features(self, checkpoint: dict[str, Any], features, where: str) -> None:
        pass  # nothing to choose

    def color_space(self, cfg: DictConfig) -> RadianceTransform:
        return RadianceTransform("none")  # linear radiance

    def training_data(self, cfg: DictConfig, features) -> tuple[ToySamples, ToySamples]:
        patches = Path(cfg.paths.prepared) / "patches"
        seed = int(cfg.seed)
        return (
            ToySamples(patches / "train" / "samples.pt", seed, shuffle=True),
            ToySamples(patches / "val" / "samples.pt", seed, shuffle=False),
        )

    def loss_terms(self, cfg: DictConfig, train_data) -> TemporalLosses:
        return TemporalLosses(
            get_loss(cfg.task.train.loss),
            self.color_space(cfg),
            weight=self.dataset["temporal_weight"],
            mode="signed",
            warp=False,
            transform="none",
        )

    def held_out(self, cfg: DictConfig, features, model) -> list[dict[str, Any]]:
        items = torch.load(Path(cfg.paths.prepared) / "full" / str(cfg.task.eval.split) / "sequences.pt")
        model.check_batch_keys({k for k, v in items[0].items() if isinstance(v, torch.Tensor)})
        return [{**item, "reference_spp": 0} for item in items]
