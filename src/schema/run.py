"""The schema of a whole run config and the check `src/run.py` makes when a job starts."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException
from pydantic import AfterValidator, Field

from src.errors import ConfigError, NrbenchError, one_line
from src.schema.checks import check
from src.schema.types import NonNegativeInt, Open, PositiveFloat, PositiveInt, Schema, passes


class Ssim(Schema):
    win_size: PositiveInt
    sigma: PositiveFloat
    k1: PositiveFloat
    k2: PositiveFloat


class Lpips(Schema):
    enabled: bool
    trunk_weights: str | None
    lin_weights: str | None
    seed: NonNegativeInt


class Flip(Schema):
    enabled: bool
    mode: Literal["hdr", "ldr"]


class NoisebaseProtocol(Schema):
    """`metrics.noisebase`: options of `metrics.protocol=noisebase` (src/metrics/noisebase_protocol.py)."""

    warmup: NonNegativeInt = 16
    fvvdp: bool = True


def _cvvdp_display(name: str) -> str:
    """One of the `cvvdp` package's SDR display models (the names come from the installed package)."""
    from src.metrics.cvvdp_metric import check_display  # lazy: reads the package's data files

    return passes(check_display, name)


class Cvvdp(Schema):
    """`metrics.cvvdp`: ColorVideoVDP (Mantiuk et al. 2024) of every sequence, tone-mapped, on an SDR
    display model at `fps` frames per second (src/metrics/cvvdp_metric.py); off by default (slow on a CPU)."""

    enabled: bool = False
    display: Annotated[str, AfterValidator(_cvvdp_display)] = "standard_fhd"
    fps: PositiveFloat = 30.0


class SppEquivalentOptions(Schema):
    """`metrics.spp_equivalent`: the samples per pixel a plain render needs to reach each denoised image's
    error, read from the held-out scenes' ladder (src/metrics/spp_equivalent.py, src/data/ladder.py)."""

    enabled: bool = True
    metric: Literal["relmse", "mse"] = "relmse"
    margin: PositiveFloat = 1.0


class Metrics(Schema):
    tonemap: Literal["clip_gamma", "reinhard_gamma", "clip"]
    gamma: PositiveFloat
    relmse_eps: PositiveFloat
    relmse_crop: NonNegativeInt
    smape_eps: PositiveFloat
    ssim: Ssim
    lpips: Lpips
    flip: Flip
    protocol: Literal["noisebase"] | None = None
    noisebase: NoisebaseProtocol = NoisebaseProtocol()
    cvvdp: Cvvdp = Cvvdp()
    spp_equivalent: SppEquivalentOptions = SppEquivalentOptions()


class Tracking(Schema):
    enabled: bool
    uri: str
    artifact_root: str
    experiment: str = Field(min_length=1)
    group: str | None


class Report(Schema):
    name: str = Field(min_length=1)
    out_dir: str
    experiment: str = Field(min_length=1)
    parent_run_id: str | None
    sweep_dir: str | None
    group: str | None
    tags: dict[str, str]
    filter: str | None
    axes: list[str] = Field(min_length=1)
    columns_by: str | None
    tables_by: str | None
    metrics: list[str] | None
    keep: Literal["latest", "all"]
    images: NonNegativeInt
    min_tile_px: PositiveInt = 256
    site: bool
    committed_ledger: str | None = None


class Ledger(Schema):
    """The reproduction ledger (src/report/ledger.py): the claims file, where it writes, the tests'
    level, commits declared to be the same code, the budget keys a row prints, and where its committed
    snapshot goes (or null)."""

    claims: str
    out_dir: str
    alpha: float = Field(gt=0, lt=1)
    equivalent_commits: list[list[str]] = []
    budget_shown: list[str] = []
    profile_order: list[str] = Field(default=["smoke", "cpu", "paper", "thesis", "bako"], min_length=1)
    snapshot: str | None = None


class Export(Schema):
    """`stage=export`: the dataset's scenes as a Noisebase sample set (src/render/noisebase_export.py)."""

    out_dir: str
    format: Literal["training", "test"]
    spp: PositiveInt
    scenes: list[str] | None
    frames: PositiveInt
    pan_deg: float


class Paths(Schema):
    root: str
    data: str
    dataset: str
    raw: str
    prepared: str
    ladder: str
    run_dir: str
    scenes: str | None = None  # the radiance-field task's scene folders


class DenoiseCompare(Schema):
    learned: list[str]
    baselines: list[str]


class VolumetricCompare(DenoiseCompare):
    selected_size: NonNegativeInt


class NerfCompare(Schema):
    models: list[str]
    scenes: list[str]


class BenchCompare(Schema):
    data: dict[str, str]  # benchmarked model -> the dataset it is composed with (src/bench/model_configs.py)


class Compare(Schema):
    """conf/compare.yaml: the models and scenes the sweeps and dvc.yaml compare, and the data the
    benchmark composes a model with."""

    denoise: DenoiseCompare
    volumetric: VolumetricCompare
    nerf: NerfCompare
    bench: BenchCompare


class Render(Schema):
    variant: Literal["auto", "cuda_ad_rgb", "llvm_ad_rgb"]


class RunSchema(Schema):
    """The root keys; `task`, `dataset` and `model` are checked by their own schemas (`validate_run`)."""

    stage: str  # which stages exist depends on the task: `stages_to_run` checks it, naming them
    seed: NonNegativeInt
    data_seed: NonNegativeInt
    device: Literal["auto", "cpu", "cuda"]
    auto_resume: bool
    skip_finished: bool
    profile_name: str
    profile_tasks: list[str] = Field(min_length=1)  # the tasks a profile has sizes for
    paths: Paths
    tracking: Tracking
    metrics: Metrics
    report: Report
    ledger: Ledger
    export: Export
    render: Render
    compare: Compare
    task: Open
    dataset: Open
    model: Open


def resolved(cfg: DictConfig) -> dict[str, Any]:
    """The config as plain data, every interpolation resolved; a resolver's own error (e.g. a bad
    `task.features` met by `${nrbench.channels:...}`) comes out as its one line."""
    try:
        return OmegaConf.to_container(cfg, resolve=True)
    except OmegaConfBaseException as err:
        cause = err
        while cause is not None and not isinstance(cause, NrbenchError):
            cause = cause.__cause__ or cause.__context__  # OmegaConf chains it as the context
        raise (cause or ConfigError(f"config: {one_line(err)}")) from None


def validate_run(cfg: DictConfig, task=None) -> dict[str, Any]:
    """Check the resolved config against the schemas: the dataset's (the job's `task` built its data kind,
    whose constructor checks `dataset:` against the kind's `schema`; built here when None), the root keys
    and the task's `schema`; then build the method once (its constructor is the schema of `model:`: keys,
    types and ranges) and drop it. Raises a one-line ConfigError; returns the resolved values."""
    from src.models.instantiate import build_method
    from src.stages import task_of

    task = task or task_of(cfg)
    kind = task.kind
    check_method_fits_task(cfg, task)
    values = resolved(cfg)
    run = check(RunSchema, values)
    if values["task"]["name"] not in values["profile_tasks"]:
        raise ConfigError(
            f"profile={values['profile_name']}: has sizes for task {values['profile_tasks']}, "
            f"not task={values['task']['name']}"
        )
    check(task.schema, values["task"], "task")
    if kind is not None and not getattr(kind, "temporal", False):
        _no_video_metrics(run.metrics, str(values["dataset"].get("name")))
    build_method(values["model"])
    return values


def method_class(target: str) -> type | None:
    """The class a model's `_target_` builds: the class itself, or a builder function's return annotation
    (None when neither says)."""
    import inspect
    import typing

    from hydra.utils import get_object

    built = get_object(target)
    if inspect.isclass(built):
        return built
    returned = typing.get_type_hints(built).get("return")
    return returned if inspect.isclass(returned) else None


def check_method_fits_task(cfg: DictConfig, task) -> None:
    """A one-line ConfigError when the model is not of the methods the task runs (a radiance field under
    task=denoise), naming the task(s) that run it: read from `model._target_` before anything is resolved
    (a model of another task may interpolate keys this task's dataset lacks), at job start and in
    stage=config, not at the first batch of a training."""
    target = OmegaConf.select(cfg, "model._target_", default=None)
    built = method_class(str(target)) if target and task.methods is not None else None
    if built is None or issubclass(built, task.methods):
        return
    fitting = [
        t for t, methods in task_methods().items() if methods is not None and issubclass(built, methods)
    ]
    hint = f"add {' or '.join(f'task={t}' for t in fitting)}" if fitting else "no task runs it"
    raise ConfigError(
        f"model={cfg.model.get('name', '?')}: a {built.__name__}, not a {task.methods.__name__}, the kind "
        f"of method task={cfg.task.name} runs; {hint}"
    )


def task_methods() -> dict[str, type | None]:
    """Each task of conf/task/ with the base class of the methods it runs (`Task.methods`)."""
    from hydra.utils import get_class

    from src.schema.command_line import CONF_DIR

    out = {}
    for path in sorted((CONF_DIR / "task").glob("*.yaml")):
        node = OmegaConf.load(path)  # a global task file (task/nerf.yaml) nests its keys under task:
        target = node.get("_target_") or OmegaConf.select(node, "task._target_")
        if target:
            out[path.stem] = getattr(get_class(str(target)), "methods", None)
    return out


def _no_video_metrics(metrics: Metrics, dataset: str) -> None:
    """A one-line ConfigError at job start (before any training) when a video metric (the Noisebase
    protocol, ColorVideoVDP) is asked of a dataset of still images: they score whole sequences."""
    asked = {
        "metrics.protocol=noisebase": metrics.protocol == "noisebase",
        "metrics.cvvdp.enabled=true": metrics.cvvdp.enabled,
    }
    settings = [setting for setting, on in asked.items() if on]
    if settings:
        raise ConfigError(
            f"{settings[0]}: scores sequences only; dataset={dataset} holds still images (use a sequence "
            "dataset: volumetric, noisebase)"
        )
