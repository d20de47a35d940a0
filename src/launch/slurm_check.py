"""What is wrong with a SLURM launch, said before anything is submitted.

A request no node of the partition can satisfy (CPUs, memory, GPUs per node, more nodes than it has, a
time limit above the partition's) is held pending by SLURM for ever, reason `PartitionConfig`, and the
sweep waits without a word. `SlurmLaunchCheck` (a Hydra callback, `conf/config.yaml`) reads the
partition's nodes with `sinfo` when a multirun starts through the submitit SLURM launcher and stops it
with one line naming the `hydra.launcher.` key, what was asked and what the partition has (exit 2).

While the sweep waits, `PendingWatch` looks at its jobs (the ids submitit's folders are named after)
every `pending_poll_s` seconds and reports, once per job, one pending for a reason that waits on a person
(a drained or down node, a partition limit, a bad constraint, QOS or account), with the `scancel` that
ends it. It also says once per sweep, in one line, what submitit warns three times per status poll
when accounting is off (`sacct` fails on small clusters).

The parsing and the rule are pure functions (`nodes_from_sinfo`, `unsatisfiable`), tested on `sinfo`
output; the callback runs `sinfo` itself.
"""

from __future__ import annotations

import logging
import re
import shutil
import subprocess
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

log = logging.getLogger("nrbench.launch")

#: The `sinfo` format `nodes_from_sinfo` reads: partition (the default one starred), node, CPUs, memory
#: (MB), generic resources, the partition's time limit.
SINFO_FORMAT = "%P|%N|%c|%m|%G|%l"
KEY = "hydra.launcher"
#: submitit's message when `sacct` fails (accounting off): logged on every status poll.
SACCT_WARNING = "Bypassing sacct error"
ACCOUNTING_OFF = (
    "launch: sacct fails here (SLURM accounting is off): submitit sees a job end by its result file only, "
    "and does not see a job that dies without one; said once per sweep (sacct itself may still print "
    "'Slurm accounting storage is disabled')"
)


@dataclass(frozen=True)
class Node:
    """One node of a partition as `sinfo` reports it; `time_limit_min` is the partition's (None: none)."""

    partition: str
    name: str
    cpus: int
    memory_mb: int
    gpus: int
    time_limit_min: float | None
    default: bool = False


def gpu_count(gres: str) -> int:
    """GPUs in a `sinfo` %G field: `(null)` 0, `gpu:4` 4, `gpu:a100:2(S:0-1),gpu:v100:1` 3."""
    total = 0
    for entry in gres.split(","):
        parts = re.sub(r"\(.*?\)", "", entry).split(":")
        if parts[0] == "gpu" and len(parts) >= 2 and parts[-1].isdigit():
            total += int(parts[-1])
    return total


def minutes(limit: str) -> float | None:
    """A SLURM time limit in minutes: `infinite`/`UNLIMITED` None; `D-HH:MM:SS`, `HH:MM:SS`, `MM:SS`, `MM`."""
    if limit.lower() in ("infinite", "unlimited", "n/a", ""):
        return None
    days, _, clock = limit.rpartition("-")
    fields = [int(f) for f in clock.split(":")]
    hours, mins, secs = {1: (0, fields[0], 0), 2: (0, *fields), 3: tuple(fields)}[len(fields)]
    return (int(days or 0) * 24 + hours) * 60 + mins + secs / 60


def nodes_from_sinfo(text: str) -> list[Node]:
    """The nodes of `sinfo -h -N -o "%P|%N|%c|%m|%G|%l"` (one line per node and partition)."""
    nodes = []
    for line in text.strip().splitlines():
        partition, name, cpus, memory, gres, limit = line.split("|")
        nodes.append(
            Node(
                partition=partition.rstrip("*"),
                name=name,
                cpus=int(cpus.rstrip("+")),
                memory_mb=int(memory.rstrip("+")),
                gpus=gpu_count(gres),
                time_limit_min=minutes(limit),
                default=partition.endswith("*"),
            )
        )
    return nodes


def unsatisfiable(launcher: dict[str, Any], nodes: list[Node]) -> str | None:
    """The one-line reason no node of the launcher's partition (its `partition`, else the default one)
    can run a job of `launcher`'s request, or None when one can. Per node: `cpus_per_task` x
    `tasks_per_node` CPUs, `mem_gb` GB, `gpus_per_node` GPUs; `nodes` nodes in all; `timeout_min` within
    the partition's limit. A node must satisfy the CPUs, memory and GPUs together."""
    wanted = launcher.get("partition")
    names = sorted({n.partition for n in nodes})
    pool = [n for n in nodes if (n.partition == wanted if wanted else n.default)]
    if not pool:
        where = f"{KEY}.partition={wanted}" if wanted else f"{KEY}.partition=null"
        return (
            f"{where}: no such partition{'' if wanted else ' (none is the default)'}; the cluster has {names}"
        )
    name = pool[0].partition
    cpus = int(launcher.get("cpus_per_task") or 1) * int(launcher.get("tasks_per_node") or 1)
    memory_mb = float(launcher.get("mem_gb") or 0) * 1024
    gpus = int(launcher.get("gpus_per_node") or 0)
    # (key, value as set, amount per node, what a node has of it, unit)
    checks = [
        ("cpus_per_task", launcher.get("cpus_per_task"), cpus, lambda n: n.cpus, "CPUs"),
        ("mem_gb", launcher.get("mem_gb"), memory_mb, lambda n: n.memory_mb, "MB"),
        ("gpus_per_node", gpus, gpus, lambda n: n.gpus, "GPUs"),
    ]
    for key, value, amount, has, unit in checks:
        if not any(has(n) >= amount for n in pool):
            largest = max(pool, key=has)
            return (
                f"{KEY}.{key}={value}: asks {amount:g} {unit} per node; no node of partition {name} has "
                f"them (largest: {has(largest)} {unit} on {largest.name}; lower it or pick another partition)"
            )
    together = [n for n in pool if all(has(n) >= amount for _, _, amount, has, _ in checks)]
    if not together:
        return (
            f"{KEY}: {cpus} CPUs, {memory_mb:g} MB and {gpus} GPUs on one node: no node of partition {name} "
            "has all three"
        )
    wanted_nodes = int(launcher.get("nodes") or 1)
    if wanted_nodes > len(together):
        return (
            f"{KEY}.nodes={wanted_nodes}: partition {name} has {len(together)} node(s) that fit the request"
        )
    limit = pool[0].time_limit_min
    timeout = launcher.get("timeout_min")
    if limit is not None and timeout is not None and float(timeout) > limit:
        return f"{KEY}.timeout_min={timeout}: above partition {name}'s time limit of {limit:g} min"
    return None


#: Pending reasons (as `squeue`'s %r shows them, short or long) that do not clear by waiting, and what
#: each means.
STUCK_REASONS = {
    "PartitionConfig": "the request exceeds what the partition allows",
    "PartitionNodeLimit": "more nodes than the partition allows",
    "PartitionTimeLimit": "a time limit above the partition's",
    "ReqNodeNotAvail": "a node it needs is down or drained",
    "DOWN, DRAINED": "a node it needs is down or drained",
    "NodeDown": "a node it needs is down",
    "BadConstraints": "constraints no node satisfies",
    "InvalidQOS": "an invalid QOS",
    "InvalidAccount": "an invalid account",
}


def stuck_jobs(squeue: str) -> list[tuple[str, str, str]]:
    """(job, reason, what it means) of each PENDING job of `squeue -h -o "%i|%T|%r"` whose reason does not
    clear by waiting (`STUCK_REASONS`); jobs waiting for resources or priority are left out."""
    stuck = []
    for line in squeue.strip().splitlines():
        job, state, reason = (line.split("|", 2) + ["", ""])[:3]
        if state != "PENDING":
            continue
        meaning = next((m for key, m in STUCK_REASONS.items() if key in reason), None)
        if meaning is not None:
            stuck.append((job, reason, meaning))
    return stuck


def submitted_jobs(submitit_folder: Path) -> list[str]:
    """The SLURM ids of the jobs submitit has submitted for this sweep (its folders are named after them)."""
    if not submitit_folder.is_dir():
        return []
    return sorted(
        p.name for p in submitit_folder.iterdir() if p.is_dir() and re.fullmatch(r"\d+(_\d+)?", p.name)
    )


def vanished(jobs: list[str], squeue: str, folder: Path) -> list[str]:
    """The jobs of `jobs` that `squeue -h -r -o "%i|..."` no longer lists and that left no result file in
    their submitit folder (`<folder>/<job>/<job>_0_result.pkl`): killed before they could write one (out of
    memory, a signal before submitit's handler was installed, a node failure, an administrator's scancel)."""
    queued = {line.split("|", 1)[0] for line in squeue.strip().splitlines()}
    return [j for j in jobs if j not in queued and not (folder / j / f"{j}_0_result.pkl").exists()]


def fail_for_submitit(folder: Path, job: str, message: str) -> None:
    """Write job `job`'s result as submitit's own handler writes a failure (`("error", text)`), so that the
    sweep waiting on it raises `message` as the job's error instead of waiting for ever."""
    from submitit.core import utils

    with utils.temporary_save_path(folder / job / f"{job}_0_result.pkl") as tmp:
        utils.cloudpickle_dump(("error", message), tmp)


class PendingWatch(threading.Thread):
    """Every `interval` seconds until stopped, this sweep's jobs (`submitted_jobs`): one stuck pending
    (`stuck_jobs`) is reported once per job and meaning; one that has left the queue without a result
    (`vanished`, at two polls in a row) is failed with that reason (`fail_for_submitit`): with accounting
    off, submitit would wait for it for ever. A daemon thread: it never holds the launch up."""

    def __init__(self, submitit_folder: Path, interval: float) -> None:
        super().__init__(daemon=True, name="nrbench-pending-watch")
        self.folder, self.interval = submitit_folder, interval
        self.stopped = threading.Event()
        self.reported: set[tuple[str, str]] = set()
        self.missing: set[str] = set()  # jobs seen vanished at the last poll

    def run(self) -> None:
        while not self.stopped.wait(self.interval):
            jobs = submitted_jobs(self.folder)
            if not jobs:
                continue
            listed = subprocess.run(
                ["squeue", "-h", "-r", "--me", "-o", "%i|%T|%r"], capture_output=True, text=True, timeout=60
            )
            if listed.returncode != 0:  # the controller is busy or restarting: look again next time
                continue
            self.report_stuck(listed.stdout, set(jobs))
            self.fail_vanished(jobs, listed.stdout)

    def report_stuck(self, squeue: str, jobs: set[str]) -> None:
        for job, reason, meaning in stuck_jobs(squeue):
            # by meaning: SLURM words one wait in several ways (`ReqNodeNotAvail, ...`, then `Nodes
            # required for job are DOWN, DRAINED ...`)
            if job in jobs and (job, meaning) not in self.reported:
                self.reported.add((job, meaning))
                log.warning(
                    "launch: job %s is pending and will stay so until someone acts: %s (%s); scancel %s "
                    "ends it",
                    job,
                    meaning,
                    reason,
                    job,
                )

    def fail_vanished(self, jobs: list[str], squeue: str) -> None:
        gone = set(vanished(jobs, squeue, self.folder))
        for job in sorted(gone & self.missing):  # twice in a row: not a result still being written
            log_file = self.folder / job / f"{job}_0_log.err"
            message = (
                f"launch: job {job} left the queue without a result (killed before it could write one: out "
                f"of memory, a signal, a node failure or scancel); its log: {log_file}"
            )
            log.error("%s", message)
            fail_for_submitit(self.folder, job, message)
        self.missing = gone - self.missing


class _OncePerSweep(logging.Filter):
    """Drops submitit's records containing `text` (each goes to its two stream handlers and to Hydra's
    log: three lines per status poll) and says `instead` once, in one line, at the first."""

    def __init__(self, text: str, instead: str) -> None:
        super().__init__()
        self.text, self.instead, self.seen = text, instead, False

    def filter(self, record: logging.LogRecord) -> bool:
        if self.text not in record.getMessage():
            return True
        if not self.seen:
            self.seen = True
            log.warning("%s", self.instead)
        return False


def is_slurm(config: DictConfig) -> bool:
    """Whether the multirun launches through Hydra's submitit SLURM launcher."""
    target = str(config.hydra.launcher.get("_target_", ""))
    return target.endswith("SlurmLauncher")


class SlurmLaunchCheck(Callback):
    """At the start of a SLURM multirun: refuse a request no node can satisfy (one line, exit 2), show
    submitit's accounting warning once, and watch for jobs stuck pending (every `pending_poll_s` seconds;
    0: no watch) until the multirun ends."""

    def __init__(self, pending_poll_s: float = 30.0) -> None:
        self.pending_poll_s = float(pending_poll_s)
        self.watch: PendingWatch | None = None
        self.accounting_filter: _OncePerSweep | None = None

    def __getstate__(self) -> dict[str, Any]:
        """Without the watch thread and the launching process's log filter: submitit pickles the
        callbacks with each job."""
        return {**self.__dict__, "watch": None, "accounting_filter": None}

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        if self.watch is not None:
            self.watch.stopped.set()
        if self.accounting_filter is not None:  # the next sweep of this process says it once again
            logging.getLogger("submitit").removeFilter(self.accounting_filter)
            self.accounting_filter = None

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        if not is_slurm(config):
            return
        self.accounting_filter = _OncePerSweep(SACCT_WARNING, ACCOUNTING_OFF)
        logging.getLogger("submitit").addFilter(self.accounting_filter)
        if shutil.which("sinfo") is None:
            log.warning("launch: sinfo not found; the SLURM request is not checked against the partition")
            return
        listed = subprocess.run(
            ["sinfo", "-h", "-N", "-o", SINFO_FORMAT], capture_output=True, text=True, timeout=60
        )
        if listed.returncode != 0:
            log.warning("launch: sinfo failed (%s); the request is not checked", listed.stderr.strip())
            return
        launcher = OmegaConf.to_container(config.hydra.launcher, resolve=True)
        reason = unsatisfiable(launcher, nodes_from_sinfo(listed.stdout))
        if reason is not None:
            log.error("%s", reason)
            raise SystemExit(2)
        if self.pending_poll_s > 0:
            folder = Path(str(launcher["submitit_folder"])).parent  # `<sweep dir>/.submitit/%j`
            self.watch = PendingWatch(folder, self.pending_poll_s)
            self.watch.start()
