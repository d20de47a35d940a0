"""Schema of `task:` for the denoising task (conf/task/denoise.yaml and its profiles): what every denoising
kind of data shares (a kind's own options are its `dataset:` schema's, src/schema/dataset.py)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from src.data.features import feature_channels
from src.schema.types import (
    AtLeastOne,
    NonNegativeFloat,
    NonNegativeInt,
    Percentile,
    PositiveFloat,
    PositiveInt,
    Probability,
    Schema,
    Target,
    known_loss,
    own_error,
    passes,
)


class Split(Schema):
    train: Probability
    val: Probability
    test: Probability

    @model_validator(mode="after")
    def _sums_to_one(self) -> Split:
        total = self.train + self.val + self.test
        if abs(total - 1.0) > 1e-6:
            raise own_error(f"task.preprocess.split: fractions sum to {total:g}; expected 1")
        return self


class Repair(Schema):
    nonfinite: Literal["error", "zero"]
    negative: Literal["error", "clamp"]
    firefly_clamp: PositiveFloat | None


class Preprocess(Schema):
    patch_size: PositiveInt
    candidates_factor: AtLeastOne
    min_keep_prob: Probability
    min_distance: NonNegativeFloat
    importance: Literal["thesis", "mc_variance"]
    importance_window: PositiveFloat
    importance_percentile: Percentile
    split: Split
    split_seed: NonNegativeInt
    split_by_base: bool
    sample_seed: NonNegativeInt
    whiten_eps: PositiveFloat
    repair: Repair


class Train(Schema):
    lr: PositiveFloat
    batch_size: PositiveInt
    loss: str | Target
    optimizer: Target
    schedule: Target | None
    epochs: PositiveInt
    max_steps: PositiveInt | None
    num_workers: NonNegativeInt
    amp: bool
    log_every: PositiveInt
    resume: str | None
    checkpoint_dir: str
    curves_file: str

    _known_loss = field_validator("loss")(classmethod(lambda cls, value: known_loss(value)))


class Eval(Schema):
    split: Literal["val", "test"]
    tile: NonNegativeInt
    save_exr: bool
    strips: bool
    crop_size: PositiveInt
    crop_zoom: PositiveInt
    checkpoint: str
    out_dir: str
    # a filter's model config scored beside the run's method (conf/task/filter_search.yaml); built, and
    # its keys checked, by the evaluation
    baseline: dict[str, Any] | None = None


class DenoiseTaskSchema(Schema):
    name: str
    target: str = Field(alias="_target_")
    stages: list[Literal["render", "preprocess", "train", "eval", "report"]]
    optional_stages: list[Literal["select_features"]]
    features: list[str]
    preprocess: Preprocess
    train: Train
    eval: Eval

    @field_validator("features")
    @classmethod
    def _known_features(cls, value: list[str]) -> list[str]:
        return passes(feature_channels, value)
