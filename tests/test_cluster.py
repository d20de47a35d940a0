"""A smoke study through Hydra's submitit SLURM launcher against a real one-node SLURM and a real MLflow
tracking server (scripts/cluster.sh, started and stopped by the fixture), beside the same study run with
the local launcher: every job FINISHED in the server, the sweep's parent run there, and the same held-out
metrics as the local runs (timings aside). Needs root (slurmctld and slurmd run as root; the script
installs Debian's slurm-wlm and munge where missing). The smoke study is part of the default suite (CI
runs it); the launch-time messages and the requeues are `-m slow`."""

from __future__ import annotations

import os
import re
import socket
import subprocess
from pathlib import Path

import mlflow
import pytest
from mlflow.tracking import MlflowClient

from tests.conftest import ROOT, cli_job, is_timed

pytestmark = pytest.mark.skipif(os.geteuid() != 0, reason="a one-node SLURM runs its daemons as root")
SCRIPT = ROOT / "scripts" / "cluster.sh"
MODELS = "cross_bilateral"  # a baseline: nothing to train, render + preprocess + eval per job
STUDY = ["profile=smoke", "metrics.lpips.enabled=false", "metrics.flip.enabled=false", "report.site=false"]
SLURM = [
    "hydra/launcher=slurm",
    "hydra.launcher.partition=debug",
    "hydra.launcher.gpus_per_node=0",
    "hydra.launcher.cpus_per_task=1",
    "hydra.launcher.mem_gb=2",
    "hydra.launcher.timeout_min=10",
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """`scripts/cluster.sh up` in a temporary folder, its environment; `down` at the end, also on failure."""
    folder = tmp_path_factory.mktemp("cluster")
    env = {**os.environ, "NRBENCH_CLUSTER_DIR": str(folder), "NRBENCH_MLFLOW_PORT": str(_free_port())}
    try:
        up = subprocess.run(["bash", str(SCRIPT), "up"], env=env, capture_output=True, text=True, timeout=600)
        assert up.returncode == 0, up.stdout + up.stderr
        exported = dict(
            line.removeprefix("export ").split("=", 1)
            for line in (folder / "cluster.env").read_text().splitlines()
            if line.startswith("export ")
        )
        yield {**env, **exported}
    finally:
        subprocess.run(["bash", str(SCRIPT), "down"], env=env, capture_output=True, timeout=120)


def _eval_metrics(uri: str) -> dict[tuple[str, str], dict[str, float]]:
    """{(model, seed): metrics} of the FINISHED job runs (sweep parents left out), timings left out."""
    mlflow.set_tracking_uri(uri)
    client = MlflowClient()
    out = {}
    for experiment in client.search_experiments():
        for run in client.search_runs([experiment.experiment_id]):
            if run.data.tags.get("nrbench.sweep_parent") == "true" or run.info.status != "FINISHED":
                continue
            metrics = {k: v for k, v in run.data.metrics.items() if k.startswith("eval_") and not is_timed(k)}
            out[(run.data.params["model.name"], run.data.params["seed"])] = metrics
    return out


def test_a_smoke_study_through_slurm_reaches_the_tracking_server_with_the_local_numbers(cluster, tmp_path):
    data = tmp_path / "data"
    local, env = cli_job(["-m", f"model={MODELS}", *STUDY, f"hydra.sweep.dir={tmp_path}/local"], data)
    ran = subprocess.run(local, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert ran.returncode == 0, (ran.stdout + ran.stderr)[-3000:]

    command, _ = cli_job(
        ["-m", f"model={MODELS}", *STUDY, *SLURM, f"hydra.sweep.dir={tmp_path}/slurm"], data, tmp_path / "s"
    )
    env = {**cluster, "NRBENCH_DATA_DIR": str(data)}  # the server, not the local SQLite file
    ran = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert ran.returncode == 0, (ran.stdout + ran.stderr)[-3000:]
    assert list((tmp_path / "slurm").rglob("*_submission.sh")), "the jobs did not go through submitit"
    # accounting is off: submitit's sacct warning, three lines per status poll before, now one line
    assert "Bypassing sacct error" not in ran.stdout + ran.stderr
    assert (ran.stdout + ran.stderr).count("sacct fails here (SLURM accounting is off)") == 1

    served = _eval_metrics(cluster["MLFLOW_TRACKING_URI"])
    assert set(served) == {(MODELS, "0")}
    mlflow.set_tracking_uri(cluster["MLFLOW_TRACKING_URI"])
    parents = mlflow.search_runs(
        search_all_experiments=True, filter_string="tags.`nrbench.sweep_parent` = 'true'"
    )
    assert len(parents) == 1 and set(parents["status"]) == {"FINISHED"}
    # the sweep's table and report, as the local launcher's: the same files, the same run counted
    assert "1 runs (parent run" in ran.stdout and "report: 1 runs" in ran.stdout + ran.stderr
    reports = {p.relative_to(tmp_path / "s" / "reports") for p in (tmp_path / "s" / "reports").rglob("*")}
    assert reports == {p.relative_to(data / "reports") for p in (data / "reports").rglob("*")}
    assert Path("denoise/index.html") in reports and Path("ledger.md") in reports
    measured_here = _eval_metrics(f"sqlite:///{data}/mlflow.db")
    assert served.keys() == measured_here.keys()
    for key, metrics in served.items():
        assert metrics.keys() == measured_here[key].keys() and len(metrics) > 10
        assert metrics == pytest.approx(measured_here[key], rel=1e-6, abs=1e-9), key


@pytest.mark.slow
@pytest.mark.parametrize(
    "request_,key",
    [
        ([], "hydra.launcher.cpus_per_task=8"),  # the launcher's defaults: 8 CPUs, 64 GB, 1 GPU
        (["hydra.launcher.cpus_per_task=1"], "hydra.launcher.mem_gb=64"),
        (["hydra.launcher.cpus_per_task=1", "hydra.launcher.mem_gb=2"], "hydra.launcher.gpus_per_node=1"),
    ],
)
def test_a_request_the_node_cannot_satisfy_is_one_line_at_launch(cluster, tmp_path, request_, key):
    """Before: the array stayed pending for ever (`PartitionConfig`) and the sweep waited without a word.
    Now the launch stops in one line naming the key, exit 2, with nothing submitted and no parent run."""
    command, _ = cli_job(
        ["-m", f"model={MODELS}", *STUDY, "hydra/launcher=slurm", "hydra.launcher.partition=debug", *request_,
         f"hydra.sweep.dir={tmp_path}/sweep"],
        tmp_path / "data",
    )  # fmt: skip
    env = {**cluster, "NRBENCH_DATA_DIR": str(tmp_path / "data")}
    ran = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert ran.returncode == 2, (ran.stdout + ran.stderr)[-2000:]
    lines = [line for line in (ran.stdout + ran.stderr).splitlines() if key in line]
    assert len(lines) == 1 and "no node of partition debug" in lines[0], ran.stdout + ran.stderr
    assert "Traceback" not in ran.stderr
    queue = subprocess.run(["squeue", "-h"], env=env, capture_output=True, text=True, timeout=60)
    assert queue.stdout.strip() == ""
    assert not list((tmp_path / "sweep").rglob("*_submission.sh"))


@pytest.mark.slow
def test_a_job_stuck_on_a_drained_node_is_reported_while_the_sweep_waits(cluster, tmp_path):
    """The node drained after the launch check: the job pends (`squeue`: nodes DOWN, DRAINED...) and the
    sweep says so once, naming the job and its `scancel`; back in service, the job runs and the sweep
    ends normally."""
    import time

    drain = ["scontrol", "update", f"NodeName={socket.gethostname().split('.')[0]}"]
    command, _ = cli_job(
        ["-m", f"model={MODELS}", *STUDY, *SLURM, f"hydra.sweep.dir={tmp_path}/sweep",
         "hydra.callbacks.slurm_check.pending_poll_s=1"],
        tmp_path / "data",
    )  # fmt: skip
    env = {**cluster, "NRBENCH_DATA_DIR": str(tmp_path / "data")}
    subprocess.run([*drain, "State=DRAIN", "Reason=test"], env=env, check=True, timeout=60)
    log = tmp_path / "sweep.log"
    try:
        with log.open("w") as out:
            job = subprocess.Popen(
                command, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT, text=True
            )
            deadline = time.monotonic() + 240
            while "is pending and will stay so" not in log.read_text() and time.monotonic() < deadline:
                assert job.poll() is None, log.read_text()[-2000:]
                time.sleep(1)
        reported = [line for line in log.read_text().splitlines() if "is pending and will stay so" in line]
        assert len(reported) == 1 and "a node it needs is down or drained" in reported[0], log.read_text()[
            -2000:
        ]
        assert re.search(r"scancel \d+", reported[0])
    finally:
        subprocess.run([*drain, "State=RESUME"], env=env, timeout=60)
    assert job.wait(timeout=600) == 0, log.read_text()[-3000:]
    assert sum("is pending and will stay so" in line for line in log.read_text().splitlines()) == 1


TRAINING = [
    "model=kpcn",
    "profile=smoke",
    "task.train.epochs=400",  # about 90 s of training in a job here: longer than the first signal comes
    "task.train.log_every=100",
    "metrics.lpips.enabled=false",
    "metrics.flip.enabled=false",
    "report.site=false",
]


def _sweep_runs(uri: str, sweep_dir) -> list:
    """The job runs (not the parent) of the sweep in `sweep_dir`, in the store at `uri`."""
    client = MlflowClient(uri)
    runs = [
        run
        for experiment in client.search_experiments()
        for run in client.search_runs([experiment.experiment_id])
        if run.data.tags.get("nrbench.sweep_dir") == str(sweep_dir)
    ]
    return [run for run in runs if run.data.tags.get("nrbench.sweep_parent") != "true"]


def _held_out(run) -> dict[str, float]:
    return {k: v for k, v in run.data.metrics.items() if k.startswith("eval_") and not is_timed(k)}


@pytest.mark.slow
def test_a_training_requeued_on_the_scheduler_resumes_to_the_uninterrupted_metrics_in_one_run(
    cluster, tmp_path
):
    """Two jobs of the same training as a local run, each its own sweep, side by side on the node:
    (a) requeued with `scontrol requeue` once its second epoch is checkpointed (SLURM kills it and starts
    it again), (b) given a time limit shorter than the training (2 min; submitit requeues it on SLURM's
    signal, `signal_delay_s` before the limit, as often as it takes). Each comes back in its run folder,
    continues its checkpoint and MLflow run, and ends as one FINISHED run with the local run's held-out
    metrics; the sweeps end normally (exit 0, parent FINISHED)."""
    import time
    from datetime import datetime

    from src.launch.slurm_check import submitted_jobs
    from src.train.checkpoint import load_checkpoint

    data = tmp_path / "data"
    local, env = cli_job(["-m", *TRAINING, f"hydra.sweep.dir={tmp_path}/local"], data)
    ran = subprocess.run(local, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert ran.returncode == 0, (ran.stdout + ran.stderr)[-3000:]
    (reference,) = _sweep_runs(f"sqlite:///{data}/mlflow.db", tmp_path / "local")
    expected = _held_out(reference)
    assert len(expected) > 10

    env = {**cluster, "NRBENCH_DATA_DIR": str(data)}
    limits = {
        "requeued": ["hydra.launcher.timeout_min=10"],
        "timed_out": [
            "hydra.launcher.timeout_min=2",
            "hydra.launcher.signal_delay_s=45",  # SLURM may signal up to 60 s early: from 15 s into the job
            "hydra.launcher.max_num_timeout=12",
        ],
    }
    sweeps = {}
    for name, limit in limits.items():
        command, _ = cli_job(
            ["-m", *TRAINING, *SLURM[:-1], *limit, f"hydra.sweep.dir={tmp_path}/{name}"],
            data,
            tmp_path / name,
        )
        log = (tmp_path / f"{name}.log").open("w")
        sweeps[name] = subprocess.Popen(command, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)

    last = tmp_path / "requeued" / "0" / "checkpoints" / "last.pt"
    deadline = time.monotonic() + 300
    while not (last.exists() and load_checkpoint(last)["epoch"] >= 2):
        assert sweeps["requeued"].poll() is None and time.monotonic() < deadline, "ended before requeued"
        time.sleep(0.5)
    assert not (last.parent / "final.pt").exists()
    (job,) = submitted_jobs(tmp_path / "requeued" / ".submitit")
    requeued_at = datetime.now().replace(microsecond=0)
    subprocess.run(["scontrol", "requeue", job], env=env, check=True, timeout=60)

    for name, sweep in sweeps.items():
        assert sweep.wait(timeout=900) == 0, (tmp_path / f"{name}.log").read_text()[-3000:]
        (run,) = _sweep_runs(cluster["MLFLOW_TRACKING_URI"], tmp_path / name)  # one run, resumed
        assert run.info.status == "FINISHED"
        assert _held_out(run) == pytest.approx(expected, rel=1e-6, abs=1e-9), name
        job_log = (tmp_path / name / "0" / "run.log").read_text()
        assert "resumed from" in job_log, name
        mlflow.set_tracking_uri(cluster["MLFLOW_TRACKING_URI"])
        parent = f"tags.`nrbench.sweep_dir` = '{tmp_path / name}' and tags.`nrbench.sweep_parent` = 'true'"
        parents = mlflow.search_runs(search_all_experiments=True, filter_string=parent)
        assert list(parents["status"]) == ["FINISHED"], name
    requeued_log = (tmp_path / "requeued" / "0" / "run.log").read_text()
    stamp = re.search(r"\[([\d-]+ [\d:]+),\d+\]\[src.train.loop\]\[INFO\] - resumed from", requeued_log)
    resumed_after = datetime.strptime(stamp.group(1), "%Y-%m-%d %H:%M:%S") - requeued_at
    timeouts = (tmp_path / "timed_out" / "0" / "run.log").read_text().count("Caught signal SIGUSR2")
    print(f"requeued job: training resumed {resumed_after.total_seconds():.0f} s after scontrol requeue")
    print(f"timed-out job: {timeouts} time-outs, each followed by a requeue and a resume")
    assert timeouts >= 1 and requeued_log.count("resumed from") == 1


@pytest.mark.slow
def test_the_ledger_command_launches_a_study_through_slurm_and_then_finds_it_done(cluster, tmp_path):
    """`python -m src.studies` with the SLURM launcher: the data job and the study's two jobs go through
    the scheduler into the tracking server; the dry run then counts both done by their digests."""
    import sys

    from tests.test_studies import TINY

    searchpath = tmp_path / "conf"
    (searchpath / "sweep").mkdir(parents=True)
    (searchpath / "sweep" / "tiny.yaml").write_text(TINY.format(sweeps=tmp_path / "sweeps", seeds="0,1"))
    command = [
        sys.executable, "-m", "src.studies", "--profile", "smoke", "--study", "tiny",
        f"hydra.searchpath=[file://{searchpath}]", "tracking.experiment=tiny-through-slurm",
        *STUDY[1:], f"report.out_dir={tmp_path}/reports", f"ledger.out_dir={tmp_path}/reports", *SLURM,
    ]  # fmt: skip
    env = {**cluster, "NRBENCH_DATA_DIR": str(tmp_path / "data")}
    ran = subprocess.run(command, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert ran.returncode == 0, (ran.stdout + ran.stderr)[-3000:]
    launched = [line for line in ran.stdout.splitlines() if line.startswith("+ ")]
    assert len(launched) == 2 and "hydra/launcher=slurm" in launched[0] and "task.stages=" in launched[0]
    assert len(list((tmp_path / "sweeps" / "tiny").rglob("*_submission.sh"))) == 2  # data job, then the study
    client = MlflowClient(cluster["MLFLOW_TRACKING_URI"])
    experiment = client.get_experiment_by_name("tiny-through-slurm")
    runs = [
        r
        for r in client.search_runs([experiment.experiment_id])
        if r.data.tags.get("nrbench.sweep_parent") != "true"
    ]
    assert sorted(r.data.params["seed"] for r in runs) == ["0", "1"]
    assert {r.info.status for r in runs} == {"FINISHED"}
    again = subprocess.run(
        [*command, "--dry-run"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300
    )
    assert again.returncode == 0 and "study tiny: 2 jobs, 2 done, 0 to run" in again.stdout, again.stdout
