"""Hydra's submitit SLURM launcher, telling the job when it is being requeued (`src.launch.requeue`).

Hydra instantiates launchers from the `hydra_plugins` package only, hence this folder.
"""

from __future__ import annotations

from typing import Any

from hydra_plugins.hydra_submitit_launcher import submitit_launcher

from src.launch.requeue import mark_requeued


class RequeueingSlurmLauncher(submitit_launcher.SlurmLauncher):
    """`checkpoint` (what submitit calls on SLURM's time-out or preemption signal, before it requeues the
    job) records the requeue, then resubmits the same job as the plugin does."""

    def checkpoint(self, *args: Any, **kwargs: Any) -> Any:
        mark_requeued()
        return super().checkpoint(*args, **kwargs)
