"""What every data kind implements (`dataset._target_`), and how a job builds its kind.

A kind is configured as a method is: its options are the `dataset:` group, resolved, passed to its
constructor and checked there against its `schema` (one line naming the `dataset.` key). A job builds its
kind once (`build_kind`, called by `Task.for_run`) and hands the object to the stages, the trainer and the
evaluation. Its methods also get the run config for what is not the data's: the task's settings and the
paths. A task declares the family of kinds it reads (`DenoisingKind` for the denoising tasks,
`MultiViewKind` for the radiance fields) and refuses another family in one line before any stage runs.

A new kind of data = one class here (or in the user's package) and one `conf/dataset/<name>.yaml` whose
`_target_` names it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from omegaconf import DictConfig
from pydantic import BaseModel

from src.errors import ConfigError
from src.schema.checks import check


class DataKind:
    """One kind of dataset. `schema` is the pydantic model of its `dataset:` group (`src/schema/dataset.py`),
    checked by the constructor; `describes` says in a few words what it is, for error lines."""

    schema: type[BaseModel] | None = None
    describes: str = "a dataset"

    def __init__(self, **options: Any) -> None:
        """`options`: the resolved `dataset:` group (`name`, `_target_` and the kind's own keys), kept as
        `self.dataset`; a one-line ConfigError naming the first key its `schema` refuses."""
        if self.schema is not None:
            check(self.schema, options, "dataset")
        self.dataset: dict[str, Any] = options
        self.name = str(options.get("name"))

    def data_dir(self, cfg: DictConfig) -> Path:
        """The data a run's `nrbench.data_fingerprint` tag identifies."""
        raise NotImplementedError

    def inputs(self, stage: str, cfg: DictConfig) -> dict[Path, str]:
        """What `stage` reads of this data, each with what produces it (see `Task.inputs`)."""
        return {}

    def check_stage(self, stage: str, cfg: DictConfig) -> None:
        """A one-line ConfigError when this data cannot serve `stage` with `cfg` (job start)."""

    def check_stages(self, stages: list[str], cfg: DictConfig) -> None:
        """`check_stage` of each of a job's stages, and what depends on the job's stages together."""
        for stage in stages:
            self.check_stage(stage, cfg)

    def resolve_at_job_start(self, cfg: DictConfig) -> None:
        """Settle, in place, config values that depend on another stage's output (see `Task`)."""

    def render(self, cfg: DictConfig) -> dict[str, Any]:
        """Render the data (or say where a user's data are read from)."""
        raise NotImplementedError

    def export_noisebase(self, cfg: DictConfig) -> list[Path]:
        """`stage=export`: the data rendered one sample per pass as a Noisebase sample set under
        `export.out_dir` (src/render/noisebase_export.py); the stores written. Only kinds that render
        scenes can."""
        raise ConfigError(
            f"dataset={self.name}: stage=export renders dataset=volumetric's sequences or "
            f"dataset=procedural's scenes, not {self.describes}"
        )


def kind_class(dataset: Any) -> type[DataKind]:
    """The class `dataset._target_` names; a one-line ConfigError when it is not a data kind."""
    from src.models.instantiate import resolve_target  # lazy: hydra

    found = resolve_target(dataset, "dataset")
    if not (isinstance(found, type) and issubclass(found, DataKind)):
        raise ConfigError(
            f"dataset._target_: {dataset.get('_target_')!r} is not a data kind; expected a subclass of "
            "src.kinds.base.DataKind (e.g. src.kinds.stills.RenderedStills)"
        )
    return found


def build_kind(cfg: DictConfig, family: type[DataKind], task: str) -> Any:
    """The data kind of this run, built from `dataset:` (resolved) once its class is known to be of the
    `family` task `task` reads: a one-line ConfigError for another family (before its options are
    resolved, which would fail less clearly), an unresolvable value or a value its schema refuses."""
    from src.schema.run import resolved  # one line for a resolver's error

    found = kind_class(cfg.dataset)
    if not issubclass(found, family):
        raise ConfigError(
            f"dataset={cfg.dataset.get('name')}: {found.describes} ({found.__module__}.{found.__name__}); "
            f"task={task} reads {family.describes}"
        )
    return found(**resolved(cfg.dataset))
