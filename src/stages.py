"""The pipeline stages ``python -m src.run`` dispatches; each reads files and writes files only.

Every stage is runnable alone (DVC calls them one at a time) and writes a JSON summary that carries
the resolved config, the git commit and the fingerprint of the data it read. A job builds its task (and
with it the data kind) once, `task_of`, and passes it to each stage it runs as `task=`; a stage called
without one builds its own.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError, DataError
from src.io.atomic import atomic_write_text
from src.provenance import data_fingerprint, result_config

log = logging.getLogger(__name__)


def task_of(cfg: DictConfig):
    """The task object `task._target_` names (src/tasks/), with its data kind: what each stage means for
    this task and these data (`Task.for_run`)."""
    from src.models.instantiate import resolve_target

    return resolve_target(cfg.task, "task").for_run(cfg)


def require_inputs(task, stage: str, cfg: DictConfig) -> None:
    """Every input `stage` reads exists; else one line naming the first missing one and what makes it.
    The task names its data (`Task.inputs`); a learned method's evaluation also needs its checkpoint,
    whatever the task."""
    needed = dict(task.inputs(stage, cfg))
    if stage == "eval" and cfg.model.learned:
        needed[Path(cfg.task.eval.checkpoint)] = "stage=train (or set task.eval.checkpoint)"
    for path, producer in needed.items():
        if not path.exists():
            raise DataError(f"{path}: not found, {stage} needs it; run {producer} first")


def _start_tracked(cfg: DictConfig, stage: str, tracker, task=None):
    """The task of a stage that logs to MLflow (`task`, or built), after checking its inputs; the run is
    tagged with the fingerprint of the data it reads."""
    task = task or task_of(cfg)
    require_inputs(task, stage, cfg)
    tracker.set_tags({"nrbench.data_fingerprint": data_fingerprint(task.data_dir(cfg))})
    return task


def render(cfg: DictConfig, tracker=None, task=None) -> dict:
    """Render the task's dataset (denoising EXRs, or multi-view scenes)."""
    return (task or task_of(cfg)).render(cfg)


def preprocess(cfg: DictConfig, tracker=None, task=None) -> dict:
    """Turn the rendered data into what training reads (denoising: KPCN inputs, patches, full images)."""
    task = task or task_of(cfg)
    require_inputs(task, "preprocess", cfg)
    return task.preprocess(cfg)


def train(cfg: DictConfig, tracker, task=None) -> dict:
    """Fit the learned model (non-learned baselines have nothing to fit); tag the run with the data's
    fingerprint and log the final checkpoint."""
    if not cfg.model.learned:
        print(f"train: {cfg.model.name} is not learned; nothing to train")
        return {}
    summary = _start_tracked(cfg, "train", tracker, task).train(cfg, tracker)
    tracker.log_artifact(summary["checkpoint"], "checkpoints")
    print(
        f"train: {cfg.model.name} {summary['steps']} steps in {summary['train_time_s']:.1f} s "
        f"-> {summary['checkpoint']}"
    )
    return summary


def search(cfg: DictConfig, tracker, task=None) -> dict:
    """Search for a method (`task=filter_search`: filter expressions by GP); logs to MLflow."""
    return _start_tracked(cfg, "search", tracker, task).search(cfg, tracker)


def select_features(cfg: DictConfig, tracker, task=None) -> dict:
    """Choose the denoiser's auxiliary features automatically (the denoising task on the volumetric
    sequences: a probe trained with feature dropout, then greedy forward selection); logs to MLflow."""
    return _start_tracked(cfg, "select_features", tracker, task).select_features(cfg, tracker)


def evaluate(cfg: DictConfig, tracker, task=None) -> dict:
    """Score the model on the held-out data; log metrics and images."""
    return _start_tracked(cfg, "eval", tracker, task).evaluate(cfg, tracker)


def report(cfg: DictConfig, tracker=None, task=None) -> dict:
    """Tables, figures and an HTML page from the logged MLflow runs (`report.*` selects them). Inside a
    multirun the sweep's callback writes one report over all its jobs when they are done instead."""
    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
        print("report: written once, over all jobs, when the sweep ends")
        return {}
    from src.report.build import build_report, report_line

    return _from_logged_runs(cfg, "report", "to report on", build_report, report_line)


def ledger(cfg: DictConfig, tracker=None, task=None) -> dict:
    """The reproduction ledger: every claim of `ledger.claims` (conf/claims.yaml) with the status the
    logged runs give it, written to `<ledger.out_dir>/ledger.{md,html,csv}` (src/report/ledger.py)."""
    from src.report.ledger import build_ledger, ledger_line

    return _from_logged_runs(cfg, "ledger", "to judge the claims by", build_ledger, ledger_line)


def _from_logged_runs(cfg: DictConfig, stage: str, purpose: str, build: Callable, line: Callable) -> dict:
    """`build(cfg)`'s summary, its `line` printed; nothing (and a line saying why) without tracking."""
    if not cfg.tracking.enabled:
        print(f"{stage}: tracking.enabled is false, so there are no logged runs {purpose}")
        return {}
    summary = build(cfg)
    print(line(summary), flush=True)
    return summary


def site(cfg: DictConfig, tracker=None, task=None) -> dict:
    """The report site under `report.out_dir` (src/report/site.py): `index.html` linking every report, study
    and the ledger, a page per method and the benchmark runs' page. Reports and the ledger rebuild it
    themselves (`report.site`); DVC runs it as its own stage, after them."""
    import mlflow

    from src.report.site import build_site

    if cfg.tracking.enabled:  # the benchmark runs come from the store
        mlflow.set_tracking_uri(str(cfg.tracking.uri))
    summary = build_site(cfg.report.out_dir, cfg.report.get("committed_ledger"))
    print(f"site: {summary['reports']} reports -> {summary['index']}")
    return summary


def export(cfg: DictConfig, tracker=None, task=None) -> dict:
    """The dataset's scenes as a Noisebase sample set under `export.out_dir` (src/render/noisebase_export.py):
    dataset=volumetric's animations, or dataset=procedural's still scenes as camera pans; the data kind
    says how (`DataKind.export_noisebase`)."""
    kind = (task or task_of(cfg)).kind
    if kind is None:
        raise ConfigError(f"task={cfg.task.name}: stage=export needs a denoising task's rendered data")
    written, e = kind.export_noisebase(cfg), cfg.export
    print(f"export: {len(written)} Noisebase {e.format}-format stores ({e.spp} spp) -> {e.out_dir}")
    return {"stores": [str(p) for p in written], "out_dir": str(e.out_dir)}


def print_model_summary(cfg: DictConfig, tracker=None, task=None) -> dict:
    """Print the model's architecture and parameter count (and FLOPs per pixel or per ray); trains
    nothing."""
    from src.models.instantiate import build_method

    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    task, model = task or task_of(cfg), build_method(model_cfg)
    print(task.model_summary(model, model_cfg))
    extra = task.training_summary(model, cfg)
    if extra:
        print(extra)
    return {}


def write_result_config(cfg: DictConfig, tracker=None, task=None) -> dict:
    """Write what decides this job's results (`provenance.result_config`) to `<paths.run_dir>/params.yaml`.

    DVC's train/eval stages depend on this file instead of on `conf/`: it changes only when a value the
    job uses changes, so editing one model's config reruns that model's stages and no other."""
    path = Path(cfg.paths.run_dir) / "params.yaml"
    atomic_write_text(path, OmegaConf.to_yaml(result_config(cfg), sort_keys=True))
    print(f"config: {cfg.model.name} -> {path}")
    return {}


STAGES: dict[str, Callable[..., dict]] = {
    "render": render,
    "preprocess": preprocess,
    "train": train,
    "search": search,
    "select_features": select_features,
    "eval": evaluate,
    "report": report,
    "ledger": ledger,
    "site": site,
    "export": export,
    "summary": print_model_summary,
    "config": write_result_config,
}
#: Stages that run outside a task's pipeline and log nothing.
STANDALONE = ("summary", "config", "ledger", "site", "export")
#: Stages whose results go to MLflow (one run per job).
TRACKED = ("train", "search", "select_features", "eval")
#: Stages that read the logged runs, so they run after the job's own MLflow run has finished.
AFTER_RUN = ("report",)


def stages_to_run(cfg: DictConfig) -> list[str]:
    """``stage=all`` runs the task's stages in order; otherwise the one named stage of the task."""
    task_stages = list(cfg.task.stages)
    unknown = [s for s in task_stages if s not in STAGES]
    if unknown:
        raise ConfigError(f"task.stages: unknown stage(s) {unknown}; expected some of {sorted(STAGES)}")
    if cfg.stage == "all":
        return task_stages
    if cfg.stage in STANDALONE or cfg.stage in cfg.task.get("optional_stages", ()):
        return [cfg.stage]
    if cfg.stage not in task_stages:
        raise ConfigError(
            f"stage: unknown stage '{cfg.stage}' for task '{cfg.task.name}'; "
            f"expected all, one of {task_stages + list(cfg.task.get('optional_stages', ()))}, "
            f"or {' / '.join(STANDALONE)}"
        )
    return [cfg.stage]
