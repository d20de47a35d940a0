"""A smoke study through Hydra's submitit SLURM launcher against a real one-node SLURM and a real MLflow
tracking server (scripts/cluster.sh, started and stopped by the fixture), beside the same study run with
the local launcher: every job FINISHED in the server, the sweep's parent run there, and the same held-out
metrics as the local runs (timings aside). Needs root (slurmctld and slurmd run as root; the script
installs Debian's slurm-wlm and munge where missing): `-m slow`, about two minutes on two cores."""

from __future__ import annotations

import os
import re
import socket
import subprocess

import mlflow
import pytest
from mlflow.tracking import MlflowClient

from tests.conftest import ROOT, cli_job

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(os.geteuid() != 0, reason="a one-node SLURM runs its daemons as root"),
]
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
            metrics = {
                k: v
                for k, v in run.data.metrics.items()
                if k.startswith("eval_") and not any(t in k for t in ("ms_per", "seconds", "time"))
            }
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
    # accounting is off: submitit's sacct warning, once per status poll before, now once per sweep
    calls = set(re.findall(r"Call #(\d+) - Bypassing sacct error", ran.stdout + ran.stderr))
    assert calls <= {"1"}, calls

    served = _eval_metrics(cluster["MLFLOW_TRACKING_URI"])
    assert set(served) == {(MODELS, "0")}
    mlflow.set_tracking_uri(cluster["MLFLOW_TRACKING_URI"])
    parents = mlflow.search_runs(
        search_all_experiments=True, filter_string="tags.`nrbench.sweep_parent` = 'true'"
    )
    assert len(parents) == 1 and set(parents["status"]) == {"FINISHED"}
    measured_here = _eval_metrics(f"sqlite:///{data}/mlflow.db")
    assert served.keys() == measured_here.keys()
    for key, metrics in served.items():
        assert metrics.keys() == measured_here[key].keys() and len(metrics) > 10
        assert metrics == pytest.approx(measured_here[key], rel=1e-6, abs=1e-9), key


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
