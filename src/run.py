"""Hydra entry point: ``python -m src.run [stage=...] [model=...] [profile=...] [overrides]``."""

from __future__ import annotations

import contextlib
import logging

import hydra
from omegaconf import DictConfig

from src.errors import NrbenchError
from src.stages import AFTER_RUN, STAGES, TRACKED, stages_to_run

log = logging.getLogger("nrbench")


def _tracked_run(cfg: DictConfig, stages: list[str]):
    """One MLflow run for this job when it trains or evaluates; a resumed training continues the MLflow
    run its checkpoint names."""
    if not any(s in TRACKED for s in stages):
        return contextlib.nullcontext(None)
    from src.tracking.mlflow_tracking import job_run
    from src.train.checkpoint import load_checkpoint
    from src.train.device import pick_device

    resume = cfg.task.get("train", {}).get("resume")
    resume_run_id = load_checkpoint(resume).get("mlflow_run_id") if resume and "train" in stages else None
    tags = {
        "nrbench.task": cfg.task.name,
        "nrbench.model": cfg.model.name,
        "nrbench.profile": cfg.profile_name,
        "nrbench.device": str(pick_device(cfg.device)),
    }
    return job_run(
        cfg, run_name=f"{cfg.model.name}-{cfg.profile_name}", tags=tags, resume_run_id=resume_run_id
    )


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> None:
    try:
        stages = stages_to_run(cfg)
        # The report reads FINISHED runs, this job's included: it runs after the job's MLflow run ends.
        in_run = [s for s in stages if s not in AFTER_RUN]
        with _tracked_run(cfg, in_run) as tracker:
            for name in in_run:
                log.info("stage %s", name)
                STAGES[name](cfg, tracker)
        for name in (s for s in stages if s in AFTER_RUN):
            log.info("stage %s", name)
            STAGES[name](cfg, None)
    except NrbenchError as err:
        # One line for the user; the traceback adds nothing for a bad input or config value.
        log.error("%s", err)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
