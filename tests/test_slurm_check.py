"""The launch-time check of a SLURM request (src/launch/slurm_check.py) on `sinfo` output: each resource
on both sides of its limit, the default partition, the time limit, and the accounting warning once. The
real scheduler refusing the launcher's defaults: tests/test_cluster.py (slow)."""

from __future__ import annotations

import logging

import pytest

from src.launch.slurm_check import (
    SACCT_WARNING,
    SlurmLaunchCheck,
    gpu_count,
    minutes,
    nodes_from_sinfo,
    unsatisfiable,
)

# Two partitions: `cpu*` (the default) with a 2-CPU node and a 16-CPU one, `gpu` with two 4-GPU nodes and a
# 2-day limit.
SINFO = """cpu*|small|2|8000|(null)|infinite
cpu*|big|16|64000|(null)|infinite
gpu|g1|32|256000|gpu:a100:4(S:0-1)|2-00:00:00
gpu|g2|32|256000|gpu:4|2-00:00:00
"""
NODES = nodes_from_sinfo(SINFO)
FITS_CPU = {"partition": None, "cpus_per_task": 16, "tasks_per_node": 1, "mem_gb": 62, "gpus_per_node": 0}
FITS_GPU = {"partition": "gpu", "cpus_per_task": 8, "mem_gb": 64, "gpus_per_node": 4, "timeout_min": 2880}


@pytest.mark.parametrize(
    "gres,count", [("(null)", 0), ("gpu:4", 4), ("gpu:a100:2(S:0-1),gpu:v100:1", 3), ("mps:100", 0)]
)
def test_gpus_are_counted_from_the_gres_field(gres, count):
    assert gpu_count(gres) == count


@pytest.mark.parametrize(
    "limit,mins",
    [
        ("infinite", None),
        ("UNLIMITED", None),
        ("2-00:00:00", 2880),
        ("01:30:00", 90),
        ("45:30", 45.5),
        ("15", 15),
    ],
)
def test_time_limits_are_read_in_minutes(limit, mins):
    assert minutes(limit) == mins


def test_sinfo_lines_become_nodes_with_the_default_partition_marked():
    assert [(n.partition, n.name, n.cpus, n.memory_mb, n.gpus, n.default) for n in NODES] == [
        ("cpu", "small", 2, 8000, 0, True),
        ("cpu", "big", 16, 64000, 0, True),
        ("gpu", "g1", 32, 256000, 4, False),
        ("gpu", "g2", 32, 256000, 4, False),
    ]
    assert NODES[2].time_limit_min == 2880 and NODES[0].time_limit_min is None


def test_a_request_one_node_fits_passes_at_each_limit():
    assert unsatisfiable(FITS_CPU, NODES) is None  # 16 CPUs, 62 GB = 63488 MB <= 64000 on `big`
    assert unsatisfiable(FITS_GPU, NODES) is None  # exactly the partition's 2 days
    assert unsatisfiable({**FITS_GPU, "nodes": 2}, NODES) is None


@pytest.mark.parametrize(
    "change,needles",
    [
        (
            {"cpus_per_task": 17},
            ["hydra.launcher.cpus_per_task=17", "17 CPUs", "partition cpu", "16 CPUs on big"],
        ),
        ({"cpus_per_task": 9, "tasks_per_node": 2}, ["hydra.launcher.cpus_per_task=9", "18 CPUs"]),
        ({"mem_gb": 63}, ["hydra.launcher.mem_gb=63", "64512 MB", "64000 MB on big"]),
        ({"gpus_per_node": 1}, ["hydra.launcher.gpus_per_node=1", "1 GPUs", "0 GPUs on small"]),
        ({"partition": "gpu", "gpus_per_node": 5}, ["gpus_per_node=5", "partition gpu", "4 GPUs on g1"]),
        ({"partition": "gpu", "timeout_min": 2881}, ["hydra.launcher.timeout_min=2881", "2880 min"]),
        ({"partition": "gpu", "nodes": 3}, ["hydra.launcher.nodes=3", "2 node(s)"]),
        ({"partition": "debug"}, ["hydra.launcher.partition=debug", "no such partition", "['cpu', 'gpu']"]),
    ],
)
def test_a_request_no_node_can_satisfy_is_one_line_naming_its_key(change, needles):
    reason = unsatisfiable({**FITS_CPU, **change}, NODES)
    assert reason is not None and "\n" not in reason
    for needle in needles:
        assert needle in reason, (needle, reason)


def test_each_resource_fitting_some_node_is_not_enough_when_no_node_has_them_all():
    """16 CPUs fit `big`, 8000 MB... and a 2-CPU node with much memory: each alone fits one node."""
    nodes = nodes_from_sinfo("p*|many_cpus|16|4000|(null)|infinite\np*|much_memory|2|64000|(null)|infinite\n")
    reason = unsatisfiable({"cpus_per_task": 16, "mem_gb": 32, "gpus_per_node": 0}, nodes)
    assert reason is not None and "on one node" in reason and "all three" in reason
    assert unsatisfiable({"cpus_per_task": 16, "mem_gb": 3, "gpus_per_node": 0}, nodes) is None


def test_without_a_default_partition_a_null_partition_is_named():
    nodes = nodes_from_sinfo("a|n1|4|1000|(null)|infinite\n")
    reason = unsatisfiable({"partition": None, "cpus_per_task": 1, "mem_gb": 0}, nodes)
    assert (
        reason is not None and "hydra.launcher.partition=null" in reason and "none is the default" in reason
    )


def test_the_accounting_warning_is_one_line_once_per_sweep(caplog, monkeypatch):
    """The callback's filter on submitit's logger: one line of ours at the first sacct warning (which
    submitit writes three times per status poll), none of submitit's own, other warnings untouched.
    Outside a SLURM multirun the callback does nothing."""
    from omegaconf import OmegaConf

    from src.launch import slurm_check

    logger = logging.getLogger("submitit")
    slurm = OmegaConf.create({"hydra": {"launcher": {"_target_": "hydra_plugins.x.SlurmLauncher"}}})
    local = OmegaConf.create({"hydra": {"launcher": {"_target_": "hydra._internal.BasicLauncher"}}})
    monkeypatch.setattr(slurm_check.shutil, "which", lambda name: None)  # no scheduler to ask here
    monkeypatch.setattr(logger, "filters", [])
    SlurmLaunchCheck().on_multirun_start(local)
    assert logger.filters == []
    check = SlurmLaunchCheck()
    check.on_multirun_start(slurm)
    with caplog.at_level(logging.WARNING):
        for call in range(3):
            logger.warning("Call #%d - %s Command sacct returned 1", call, SACCT_WARNING)
        logger.warning("something else")
        logger.warning("something else")
    messages = [r.getMessage() for r in caplog.records if r.name == "submitit"]
    assert not any(SACCT_WARNING in m for m in messages) and messages.count("something else") == 2
    ours = [r.getMessage() for r in caplog.records if r.name == "nrbench.launch"]
    assert ours.count(slurm_check.ACCOUNTING_OFF) == 1
    # A sweep's end takes its filter away: a second sweep in the same process says it once, not never,
    # and the filters do not pile up.
    check.on_multirun_end(slurm)
    assert logger.filters == []
    check.on_multirun_start(slurm)
    with caplog.at_level(logging.WARNING):
        logger.warning("Call #1 - %s Command sacct returned 1", SACCT_WARNING)
    ours = [r.getMessage() for r in caplog.records if r.name == "nrbench.launch"]
    assert ours.count(slurm_check.ACCOUNTING_OFF) == 2 and len(logger.filters) == 1


def test_a_job_pending_for_a_reason_that_will_not_clear_is_picked_out():
    from src.launch.slurm_check import stuck_jobs

    squeue = "\n".join(
        [
            "12_0|PENDING|Nodes required for job are DOWN, DRAINED or reserved for jobs in higher priority "
            "partitions",  # squeue's %r of a drained node (SLURM 22.05)
            "12_1|PENDING|PartitionConfig",
            "12_2|PENDING|Resources",  # waits for a free node: clears by itself
            "12_3|PENDING|Priority",
            "13|RUNNING|None",
            "14|PENDING|(ReqNodeNotAvail, UnavailableNodes:g1)",
        ]
    )
    stuck = stuck_jobs(squeue)
    assert [(job, meaning) for job, _, meaning in stuck] == [
        ("12_0", "a node it needs is down or drained"),
        ("12_1", "the request exceeds what the partition allows"),
        ("14", "a node it needs is down or drained"),
    ]
    assert stuck_jobs("") == [] and stuck_jobs("15|RUNNING|PartitionConfig") == []


def test_the_sweeps_jobs_are_the_folders_submitit_named_after_them(tmp_path):
    from src.launch.slurm_check import submitted_jobs

    assert submitted_jobs(tmp_path / "absent") == []
    for name in ("7_0", "7_1", "8", "not_a_job"):
        (tmp_path / name).mkdir()
    (tmp_path / "9").write_text("a file, not a job folder")
    assert submitted_jobs(tmp_path) == ["7_0", "7_1", "8"]


def test_a_job_gone_from_the_queue_without_a_result_fails_the_sweep_in_submitits_own_terms(tmp_path):
    """With accounting off, submitit sees a job end by its result file only: one killed before writing it
    (here: the time-out signal before submitit's handler was installed, exit 140) kept the sweep waiting
    for ever. Two polls without it in `squeue` and without a result: the job's result is written as
    submitit writes a failure, and submitit's own reader raises it."""
    import submitit

    from src.launch.slurm_check import PendingWatch, vanished

    for job in ("7_0", "7_1", "8"):
        (tmp_path / job).mkdir()
    (tmp_path / "7_1" / "7_1_0_result.pkl").write_bytes(b"a result")
    squeue = "8|PENDING|BeginTime"  # 8 is requeued, waiting to start again: not gone
    assert vanished(["7_0", "7_1", "8"], squeue, tmp_path) == ["7_0"]
    assert vanished(["7_0", "7_1", "8"], "7_0|RUNNING|None\n" + squeue, tmp_path) == []

    watch = PendingWatch(tmp_path, interval=1)
    watch.fail_vanished(["7_0", "7_1", "8"], squeue)  # first poll: maybe still writing its result
    assert not (tmp_path / "7_0" / "7_0_0_result.pkl").exists()
    watch.fail_vanished(["7_0", "7_1", "8"], squeue)
    assert (tmp_path / "7_0" / "7_0_0_result.pkl").exists()
    assert (tmp_path / "7_1" / "7_1_0_result.pkl").read_bytes() == b"a result"  # its own is kept
    job = submitit.SlurmJob(folder=tmp_path / "%j", job_id="7_0")
    with pytest.raises(submitit.core.utils.FailedJobError, match="left the queue without a result"):
        job.result()
    watch.fail_vanished(["7_0", "7_1", "8"], squeue)  # written once: nothing vanished any more
    assert watch.missing == set()


def test_a_job_back_in_the_queue_between_two_polls_is_not_failed(tmp_path):
    from src.launch.slurm_check import PendingWatch

    (tmp_path / "5").mkdir()
    watch = PendingWatch(tmp_path, interval=1)
    watch.fail_vanished(["5"], "")
    watch.fail_vanished(["5"], "5|PENDING|BeginTime")
    watch.fail_vanished(["5"], "")
    assert not (tmp_path / "5" / "5_0_result.pkl").exists()


def test_the_callback_pickles_without_its_thread_and_filter(monkeypatch, tmp_path):
    """submitit pickles the Hydra callbacks with every job: the watch thread cannot be pickled, and the
    launching process's log filter has no business in a job."""
    import pickle

    from omegaconf import OmegaConf

    from src.launch import slurm_check

    monkeypatch.setattr(slurm_check.shutil, "which", lambda name: None)
    monkeypatch.setattr(logging.getLogger("submitit"), "filters", [])
    check = SlurmLaunchCheck(pending_poll_s=5)
    check.on_multirun_start(OmegaConf.create({"hydra": {"launcher": {"_target_": "x.SlurmLauncher"}}}))
    check.watch = slurm_check.PendingWatch(tmp_path, 5)
    copy = pickle.loads(pickle.dumps(check))
    assert copy.watch is None and copy.accounting_filter is None and copy.pending_poll_s == 5
    assert check.accounting_filter is not None  # the original keeps its own
