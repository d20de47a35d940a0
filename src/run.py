"""Hydra entry point: ``python -m src.run [stage=...] [model=...] [profile=...] [overrides]``."""

from __future__ import annotations

import contextlib
import logging
from pathlib import Path

import hydra
from omegaconf import DictConfig

from src.errors import NrbenchError
from src.provenance import config_digest
from src.schema.run import validate_run
from src.stages import AFTER_RUN, STAGES, TRACKED, stages_to_run, task_of
from src.tracking.peak_memory import PeakMemory

log = logging.getLogger("nrbench")


def _run_to_continue(cfg: DictConfig, stages: list[str]) -> str | None:
    """The MLflow run this job appends to: a resumed training, probe or search (an explicit resume, or a
    requeued job finding its own checkpoint: `auto_resume`) continues its checkpoint's run, and an
    evaluation of a trained checkpoint (e.g. DVC's separate eval stage) logs into the run that trained it,
    so one run holds a model's training curves and test metrics."""
    from src.train.checkpoint import checkpoint_run_id, resumable_checkpoint

    if "search" in stages:
        from src.gp.search import saved_job
        from src.tasks.filter_search import resumable_search_state

        state = resumable_search_state(cfg)
        return saved_job(state).get("mlflow_run_id") if state else None
    if "train" in stages:
        checkpoint = resumable_checkpoint(cfg)
    elif "select_features" in stages:
        from src.train.select_features import probe_config

        checkpoint = resumable_checkpoint(probe_config(cfg))
    elif "eval" in stages and cfg.model.get("learned", False):
        checkpoint = cfg.task.get("eval", {}).get("checkpoint")
        checkpoint = checkpoint if checkpoint and Path(checkpoint).is_file() else None
    else:
        checkpoint = None
    return checkpoint_run_id(checkpoint) if checkpoint else None


def _tracked_run(cfg: DictConfig, stages: list[str]):
    """One MLflow run for this job when it trains or evaluates (see `_run_to_continue`)."""
    if not any(s in TRACKED for s in stages):
        return contextlib.nullcontext(None)
    from src.tracking.finished import DIGEST_TAG
    from src.tracking.mlflow_tracking import job_run
    from src.train.device import device_card, pick_device, precision

    device = pick_device(cfg.device)
    tags = {
        "nrbench.task": cfg.task.name,
        "nrbench.model": cfg.model.name,
        "nrbench.profile": cfg.profile_name,
        "nrbench.device": str(device),
        "nrbench.precision": precision(bool(cfg.task.train.get("amp", False)), device),
        **{f"nrbench.{key}": value for key, value in device_card(device).items()},
    }
    if cfg.tracking.get("group"):
        tags["nrbench.group"] = str(cfg.tracking.group)
    if cfg.stage == "all":  # what `skip_finished` and `python -m src.studies` count as this config done
        tags[DIGEST_TAG] = config_digest(cfg)
    return job_run(
        cfg,
        run_name=f"{cfg.model.name}-{cfg.profile_name}",
        tags=tags,
        resume_run_id=_run_to_continue(cfg, stages),
    )


def _finished_already(cfg: DictConfig, stages: list[str]) -> str | None:
    """With `skip_finished`, the FINISHED run of a whole job (`stage=all`) of this same configuration in
    the tracking store, if there is one (a rerun of a study continues only the jobs not done)."""
    if not (cfg.get("skip_finished", False) and cfg.stage == "all" and cfg.tracking.enabled):
        return None
    from src.tracking.finished import finished_runs

    digest = config_digest(cfg)
    done = finished_runs(str(cfg.tracking.uri), str(cfg.tracking.experiment), digest).get(digest)
    return done.run_id if done else None


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> dict[str, dict]:
    """Run the selected stages; returns each stage's summary by stage name (a sweeper reads its
    objective from it, e.g. `train.val_loss_color`)."""
    results: dict[str, dict] = {}
    try:
        task = task_of(cfg)  # with its data kind, built once for the whole job
        validate_run(cfg, task)  # every value checked before any data is read or any file written
        stages = stages_to_run(cfg)
        task.resolve_at_job_start(cfg)
        task.check_stages(stages, cfg)
        done = _finished_already(cfg, stages)
        if done is not None:
            log.info("skipped: this configuration already has a FINISHED run (%s; skip_finished)", done)
            return {"skipped": {"run_id": done}}
        # The report reads FINISHED runs, this job's included: it runs after the job's MLflow run ends.
        in_run = [s for s in stages if s not in AFTER_RUN]
        with _tracked_run(cfg, in_run) as tracker:
            for name in in_run:
                log.info("stage %s", name)
                with PeakMemory() as peak:
                    results[name] = STAGES[name](cfg, tracker, task=task)
                if tracker is not None:  # the stage's cost card: its peak memory
                    tracker.log_metrics(peak.metrics(name))
        for name in (s for s in stages if s in AFTER_RUN):
            log.info("stage %s", name)
            results[name] = STAGES[name](cfg, None, task=task)
        return results
    except NrbenchError as err:
        # One line for the user; the traceback adds nothing for a bad input or config value.
        log.error("%s", err)
        _remove_rejected_run_dir()
        raise SystemExit(2) from None


#: What Hydra writes into a job's folder before the job's own code runs: nothing else means the job made
#: nothing, and a rejected one leaves no folder.
_HYDRA_FILES = {".hydra", "run.log", "main.log"}


def _remove_rejected_run_dir() -> None:
    """Delete this job's output folder when it holds only what Hydra wrote, and Hydra's date folder above
    it when that is left empty: a command rejected at job start leaves no `outputs/<date>/<time>/`. A
    folder with anything else (a resumed job's checkpoints, what an earlier job wrote) is kept, and so is
    the folder above a `hydra.run.dir` given on the command line."""
    import shutil

    from hydra.core.hydra_config import HydraConfig
    from hydra.types import RunMode

    try:
        hydra_cfg = HydraConfig.get()
    except ValueError:  # not under Hydra (a test calling main's body)
        return
    if hydra_cfg.mode != RunMode.RUN:
        return
    folder = Path(hydra_cfg.runtime.output_dir)
    if not folder.is_dir() or any(p.name not in _HYDRA_FILES for p in folder.iterdir()):
        return
    logging.shutdown()  # the log file handler closes before its file goes
    shutil.rmtree(folder, ignore_errors=True)
    if not any(o.startswith("hydra.run.dir=") for o in hydra_cfg.overrides.hydra):
        with contextlib.suppress(OSError):
            folder.parent.rmdir()  # Hydra's date folder, when this was its only job


def _check_command_line() -> None:
    """A misspelt group option or unknown key on the command line: one line and exit status 2, before
    Hydra composes anything or makes a folder (`src.schema.command_line`)."""
    import sys

    from src.schema.command_line import check_command_line

    try:
        check_command_line(sys.argv[1:])
    except NrbenchError as err:
        print(f"[nrbench][ERROR] - {err}", file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    _check_command_line()
    main()
