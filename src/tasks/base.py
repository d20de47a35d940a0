"""What a task is: the object `task._target_` names, which says what each stage means for it (see
`src/stages.py`, which calls these methods and has no task-name branches). A new task subclasses `Task`,
implements the stages its `task.stages` list names, and ships a `conf/task/<name>.yaml`.

A task that reads data names the family of data kinds it reads (`kinds`, `src/kinds/`); a job builds its
task once (`Task.for_run`) with the data kind `dataset._target_` names, built once too. What a stage
reads, which stages the data can serve and how they are rendered is then the kind's, and the task adds
only what is its own: it hands the kind to its trainer and evaluation and prints their lines."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig
from pydantic import BaseModel

from src.kinds.base import DataKind, build_kind


class Task:
    """One task (denoising, radiance fields, ...). Each method gets the resolved run config; `train` and
    `evaluate` also get the MLflow tracker of the job's run. Every method returns the stage's summary.
    `schema` is the pydantic model of its `task:` group (`src/schema/`), checked when a job starts;
    `kinds` the family of data kinds it reads (None: none); `methods` the base class of the methods it runs
    (None: any), checked when a job starts (`src.schema.run.validate_run`)."""

    schema: type[BaseModel]
    kinds: type[DataKind] | None = None
    methods: type | None = None

    def __init__(self, kind: Any = None) -> None:
        """`kind`: the run's data kind (None for a task that reads none)."""
        self.kind = kind

    @classmethod
    def for_run(cls, cfg: DictConfig) -> Task:
        """This task with the data kind `dataset._target_` names, built from `dataset:` and checked to be
        of the task's family (`src.kinds.base.build_kind`: a one-line ConfigError otherwise, or for a
        value the kind's schema refuses)."""
        return cls(None if cls.kinds is None else build_kind(cfg, cls.kinds, str(cfg.task.name)))

    def inputs(self, stage: str, cfg: DictConfig) -> dict[Path, str]:
        """What `stage` reads, each with what produces it (a stage or command), so that a stage started too
        early says what to run first instead of failing on a missing file: the data kind's. (A learned
        method's checkpoint, which every task's evaluation needs, is added by `stages.require_inputs`.)"""
        return {} if self.kind is None else self.kind.inputs(stage, cfg)

    def resolve_at_job_start(self, cfg: DictConfig) -> None:
        """Settle, in place, the config values that depend on another stage's output (read once, when a job
        starts, after the schema check and before any stage runs; a missing output is a one-line
        ConfigError): the data kind's."""
        if self.kind is not None:
            self.kind.resolve_at_job_start(cfg)

    def check_stages(self, stages: list[str], cfg: DictConfig) -> None:
        """Raise a one-line ConfigError when this config cannot run one of `stages` (checked at job start,
        before any stage runs): the data kind's refusals."""
        if self.kind is not None:
            self.kind.check_stages(stages, cfg)

    def data_dir(self, cfg: DictConfig) -> Path:
        """The data a run's `nrbench.data_fingerprint` tag identifies."""
        return self.kind.data_dir(cfg)

    def render(self, cfg: DictConfig) -> dict[str, Any]:
        """Produce (or locate) the task's dataset."""
        return self.kind.render(cfg)

    def preprocess(self, cfg: DictConfig) -> dict[str, Any]:
        """Turn the rendered data into what training reads; only tasks listing the stage implement it."""
        raise NotImplementedError

    def train(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        """Fit `cfg.model`; the summary holds at least `checkpoint`, `steps` and `train_time_s`."""
        raise NotImplementedError

    def search(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        """Search for a method (only tasks listing the stage implement it: `task=filter_search`)."""
        raise NotImplementedError

    def evaluate(self, cfg: DictConfig, tracker) -> dict[str, Any]:
        """Score the model on the held-out data (`src/eval/loop.py::Evaluation` does the loop)."""
        raise NotImplementedError

    def model_summary(self, model, model_cfg: dict) -> str:
        """The text of `stage=summary`: architecture, parameters, cost."""
        raise NotImplementedError

    def training_summary(self, model, cfg: DictConfig) -> str:
        """Lines `stage=summary` adds after `model_summary` about training with `cfg` (default: none)."""
        return ""
