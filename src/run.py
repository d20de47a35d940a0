"""Hydra entry point: ``python -m src.run [stage=render|preprocess|all] [profile=...] [overrides]``."""

from __future__ import annotations

import logging

import hydra
from omegaconf import DictConfig

from src.errors import NrbenchError
from src.stages import STAGES, stages_to_run

log = logging.getLogger("nrbench")


@hydra.main(version_base="1.3", config_path="../conf", config_name="config")
def main(cfg: DictConfig) -> None:
    try:
        for name in stages_to_run(cfg):
            log.info("stage %s", name)
            STAGES[name](cfg)
    except NrbenchError as err:
        # One line for the user; the traceback adds nothing for a bad input or config value.
        log.error("%s", err)
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
