"""Hydra callback: one report over a multirun's jobs when it ends (inside a multirun the `report` stage
does not run in each job), then the reproduction ledger again, so that the claims the sweep tests are
current. Configured in `conf/config.yaml` under `hydra.callbacks.sweep_report`, after
`mlflow_sweep`, whose parent-run record in the sweep dir says which runs are this sweep's."""

from __future__ import annotations

import logging
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from src.errors import NrbenchError
from src.multirun import read_parent, resolved_section, sweep_dir

log = logging.getLogger("nrbench.report")


class SweepReportCallback(Callback):
    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        """The report over this sweep's child runs. A report failure is logged; it does not fail the
        finished sweep."""
        # Imported here, not at the top: Hydra builds this callback in every `python -m src.run`, and the
        # report's matplotlib and mlflow cost seconds a process.
        from src.report.build import build_report, report_line

        tracking = resolved_section(config, "tracking")
        record = read_parent(sweep_dir(config))
        if not tracking.enabled or record is None:
            return
        report = OmegaConf.merge(
            resolved_section(config, "report"), {"parent_run_id": record["run_id"], "sweep_dir": None}
        )
        try:
            summary = build_report(OmegaConf.create({"report": report, "tracking": tracking}))
        except NrbenchError as err:
            log.error("report: %s", err)
            return
        print(report_line(summary), flush=True)
        self._refresh_ledger(config, tracking)

    @staticmethod
    def _refresh_ledger(config: DictConfig, tracking: DictConfig) -> None:
        """The ledger again, so the claims this sweep tests show its runs (a failure is logged)."""
        from src.report.ledger import build_ledger, ledger_line

        try:
            summary = build_ledger(
                OmegaConf.create({"ledger": resolved_section(config, "ledger"), "tracking": tracking})
            )
        except NrbenchError as err:
            log.error("ledger: %s", err)
            return
        print(ledger_line(summary), flush=True)
