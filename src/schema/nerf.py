"""Schema of `task:` for the radiance-field task (conf/task/nerf.yaml and its profiles)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from src.schema.types import NonNegativeInt, PositiveFloat, PositiveInt, Schema, Target


class Train(Schema):
    max_steps: PositiveInt
    batch_size: PositiveInt
    micro_batch_rays: PositiveInt | None
    cpu_micro_batch_rays: PositiveInt | None = None
    amp: bool = False
    batching: Literal["all_images", "single_image"]
    lr_init: PositiveFloat
    schedule: Target | None
    optimizer: Target
    grad_max_norm: PositiveFloat | None
    precrop_iters: NonNegativeInt
    precrop_frac: float = Field(gt=0, le=1)
    max_train_images: PositiveInt | None
    max_val_images: PositiveInt | None
    val_rays: PositiveInt
    chunk: PositiveInt
    cpu_chunk: PositiveInt | None = None
    log_every: PositiveInt
    val_every: PositiveInt
    checkpoint_every: PositiveInt
    resume: str | None
    checkpoint_dir: str
    curves_file: str


class Eval(Schema):
    split: Literal["val", "test"]
    max_images: PositiveInt | None
    chunk: PositiveInt
    cpu_chunk: PositiveInt | None = None
    save_images: bool
    quantize_metrics: bool
    checkpoint: str
    out_dir: str


class NerfTaskSchema(Schema):
    name: str
    target: str = Field(alias="_target_")
    stages: list[Literal["render", "train", "eval", "report"]]
    scene: str = Field(min_length=1)
    train: Train
    eval: Eval
