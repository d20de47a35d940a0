"""Requeue on time-out and preemption, with Hydra's submitit SLURM launcher.

submitit asks SLURM for a signal `signal_delay_s` before the time limit (and SLURM sends it on preemption
where the cluster is set up to); its handler calls the launcher's `checkpoint`, requeues the job with
`scontrol requeue` (up to `max_num_timeout` times after a time-out) and exits. The restarted job runs the
same Hydra job in the same run folder, where every long stage finds its newest checkpoint (`auto_resume`).

The launcher (`hydra_plugins/nrbench_slurm_launcher`) adds one fact to that, kept here: this job is being
requeued, so its MLflow run ends KILLED (the restarted job reopens it) and the sweep's parent run is not
marked failed (`requeue_pending`).
"""

from __future__ import annotations

import logging
import threading

log = logging.getLogger("nrbench")

#: Set once in a job process: the job exits right after, to start again.
REQUEUED = threading.Event()


def mark_requeued() -> None:
    """Record that this process's job is being checkpointed for a requeue (called by the launcher)."""
    REQUEUED.set()
    log.warning("requeued (time-out or preemption): the job will continue from its newest checkpoint")


def requeue_pending() -> bool:
    """Whether this process's job has been checkpointed for a requeue (it is exiting to start again)."""
    return REQUEUED.is_set()
