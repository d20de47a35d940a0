"""`bash scripts/mlflow_ui.sh`: MLflow's UI on the project's store, with web workers fitted to the cores,
MLflow's GenAI job runner off, and experiments opening on their runs in a fresh browser (MLflow 3.17
decides an experiment's view from a browser setting, not from the experiment; the app plugin
mlflow_plugins/nrbench_runs_view sets it where the browser has none: tests/test_runs_view.py)."""

import os
import shutil
import socket
import subprocess
import time
import urllib.request

import pytest
from mlflow.tracking import MlflowClient
from nrbench_runs_view import default_view_script

from src.tracking.experiment import run_url_line
from tests.conftest import ROOT

SCRIPT = str(ROOT / "scripts" / "mlflow_ui.sh")


def _url(line: str) -> str:
    return line.split("open ", 1)[1].strip()


def _script(tmp_path, *args, cores=None, jobs=None):
    """(first line, second line, the mlflow command line, its MLFLOW_SERVER_ENABLE_JOB_EXECUTION) of the
    script run from a copy of its folder layout whose `.venv/bin/mlflow` is a stand-in printing those;
    `cores`: what a stand-in `nproc` on the PATH answers. (`mlflow` itself starts in ~3 s; that it takes
    these arguments: the help test below and the slow browser test.)"""
    root = tmp_path / "repo"
    if not root.exists():
        (root / "scripts").mkdir(parents=True)
        shutil.copy(SCRIPT, root / "scripts" / "mlflow_ui.sh")
        (root / ".venv" / "bin").mkdir(parents=True)
        (root / ".venv" / "bin" / "mlflow").write_text(
            '#!/bin/sh\necho "$@"\necho "$MLFLOW_SERVER_ENABLE_JOB_EXECUTION"\n'
        )
        (root / ".venv" / "bin" / "mlflow").chmod(0o755)
    env = {**os.environ, "MLFLOW_TRACKING_URI": "sqlite:///m.db"}
    env.pop("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", None)
    if jobs is not None:
        env["MLFLOW_SERVER_ENABLE_JOB_EXECUTION"] = jobs
    if cores is not None:
        bin_dir = tmp_path / "bin"
        bin_dir.mkdir(exist_ok=True)
        (bin_dir / "nproc").write_text(f"#!/bin/sh\necho {cores}\n")
        (bin_dir / "nproc").chmod(0o755)
        env["PATH"] = f"{bin_dir}:{env['PATH']}"
    out = subprocess.run(
        ["bash", str(root / "scripts" / "mlflow_ui.sh"), *args], capture_output=True, text=True, env=env
    )
    assert out.returncode == 0, out.stderr[-2000:]
    first, second, command, job_runner = out.stdout.splitlines()
    return first, second, command, job_runner


def test_the_script_prints_the_experiments_url_and_what_makes_them_open_on_their_runs(tmp_path):
    first, second, _, _ = _script(tmp_path, "--port", "5123", cores=2)
    assert first == (
        "mlflow ui: sqlite:///m.db, 1 worker(s) for 2 core(s), job runner off -> open "
        "http://127.0.0.1:5123/#/experiments"
    )
    assert _url(first) == "http://127.0.0.1:5123/#/experiments"
    assert second.strip() == (
        "experiments open on their runs (the sidebar's GenAI | Model training switch: Model training until "
        "picked); a job's run URL opens its run"
    )


def test_the_script_starts_the_runs_view_app_unless_the_caller_names_one(tmp_path):
    _, ours, command, job_runner = _script(tmp_path, "--port", "5123", cores=2)
    start = "ui --backend-store-uri sqlite:///m.db --host 127.0.0.1 --port 5123 --workers 1"
    assert (command, job_runner) == (f"{start} --app-name nrbench --port 5123", "false")
    _, theirs, command, _ = _script(tmp_path, "--port", "5123", "--app-name", "basic-auth", cores=2)
    assert command == f"{start} --port 5123 --app-name basic-auth"
    assert _script(tmp_path, "--port", "5123", "--app-name=basic-auth", cores=2)[2] == (
        f"{start} --port 5123 --app-name=basic-auth"
    )
    assert "open on their runs" in ours and "the caller's app" in theirs and "GenAI until picked" in theirs


def test_mlflows_cli_offers_the_runs_view_app_and_the_options_the_script_passes():
    out = subprocess.run(
        [str(ROOT / ".venv" / "bin" / "mlflow"), "ui", "--help"], capture_output=True, text=True
    )
    assert out.returncode == 0, out.stderr[-2000:]
    assert "--app-name [nrbench|basic-auth]" in out.stdout
    assert all(f"{flag} " in out.stdout for flag in ("--backend-store-uri", "--host", "--port", "--workers"))


@pytest.mark.parametrize(("cores", "workers"), [(2, 1), (7, 1), (8, 2), (15, 3), (64, 4)])
def test_one_web_worker_per_four_cores_from_one_to_four(tmp_path, cores, workers):
    first, _, command, _ = _script(tmp_path, cores=cores)
    assert f", {workers} worker(s) for {cores} core(s)," in first
    assert f" --workers {workers} --app-name nrbench" in command


def test_the_callers_workers_and_job_runner_win(tmp_path):
    start = "ui --backend-store-uri sqlite:///m.db --host 127.0.0.1 --port 5000 --app-name nrbench"
    first, _, command, _ = _script(tmp_path, "-w", "3", cores=2)
    assert ", 3 worker(s) for 2 core(s), job runner off " in first
    assert command == f"{start} -w 3"  # the caller's flag alone
    first, _, command, _ = _script(tmp_path, "--workers=6", cores=2)
    assert ", 6 worker(s) " in first and command == f"{start} --workers=6"
    first, _, _, job_runner = _script(tmp_path, cores=2, jobs="true")
    assert ", job runner on " in first and job_runner == "true"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _processes(root_pid: int) -> list[str]:
    """The command lines of the process group `root_pid` leads (the script's mlflow and what it started)."""
    out = subprocess.run(["ps", "-ww", "-o", "args=", "-g", str(root_pid)], capture_output=True, text=True)
    return out.stdout.splitlines()


@pytest.mark.slow
def test_an_experiment_opens_on_its_runs_in_a_fresh_browser(tmp_path, browser):
    """~1 min on 2 cores. Clicking an experiment on the printed page shows its runs in a fresh browser, also
    in a browser where the page's script is cut out of the response (MLflow's own page): there the
    GenAI overview. A browser that picked GenAI keeps it after a reload; a job's printed run URL opens the
    run."""
    from playwright.sync_api import sync_playwright

    uri = f"sqlite:///{tmp_path}/m.db"
    client = MlflowClient(uri)
    tags = {"mlflow.experimentKind": "custom_model_development"}
    experiment = client.create_experiment("nrbench-denoise", (tmp_path / "art").as_uri(), tags=tags)
    run_id = client.create_run(experiment, run_name="kpcn-cpu").info.run_id
    client.set_terminated(run_id)
    port = _free_port()
    env = {**os.environ, "MLFLOW_TRACKING_URI": uri}
    env.pop("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", None)
    command = ["bash", SCRIPT, "--port", str(port)]
    ui = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=env, start_new_session=True)
    try:
        url = _url(ui.stdout.readline())
        deadline = time.monotonic() + 90
        while True:
            try:
                urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=2)
                break
            except OSError:
                assert time.monotonic() < deadline, "mlflow ui did not start in 90 s"
                time.sleep(1)
        server = [p for p in _processes(ui.pid) if "uvicorn" in p]
        cores = len(os.sched_getaffinity(0))
        assert len(server) == 1 and f"--workers {min(max(cores // 4, 1), 4)} " in server[0]
        assert server[0].endswith(" nrbench_runs_view:app")
        assert not [p for p in _processes(ui.pid) if "huey" in p or "_job_runner" in p]  # job runner off
        with sync_playwright() as p:
            chromium = p.chromium.launch(executable_path=shutil.which("chromium"))

            def open_experiment(page):
                page.get_by_role("link", name="nrbench-denoise", exact=True).first.click()

            fresh = chromium.new_context().new_page()
            fresh.goto(url)
            open_experiment(fresh)
            fresh.get_by_text("kpcn-cpu").first.wait_for(timeout=30_000)  # the runs table
            assert f"#/experiments/{experiment}/runs?" in fresh.url

            plain = chromium.new_context().new_page()  # MLflow's page: the response without the script

            def without_script(route):
                response = route.fetch()
                route.fulfill(response=response, body=response.body().replace(default_view_script(), b""))

            plain.route(f"http://127.0.0.1:{port}/", without_script)
            plain.goto(url)
            open_experiment(plain)
            # MLflow's default: the GenAI overview (its Usage / Quality / Tool calls tabs), no runs table
            plain.get_by_text("Tool calls", exact=True).wait_for(timeout=30_000)
            assert plain.get_by_text("kpcn-cpu").count() == 0

            genai = chromium.new_context().new_page()
            genai.goto(url)
            genai.get_by_text("GenAI", exact=True).first.click()
            genai.goto("about:blank")
            genai.goto(url)  # the page's script runs again and keeps the pick
            open_experiment(genai)
            genai.get_by_text("Tool calls", exact=True).wait_for(timeout=30_000)
            assert genai.get_by_text("kpcn-cpu").count() == 0

            line = run_url_line(uri, experiment, run_id)
            run_page = line.split()[2].replace(":5000/", f":{port}/")
            direct = chromium.new_context().new_page()
            direct.goto(run_page)
            direct.get_by_text("kpcn-cpu").first.wait_for(timeout=30_000)
            assert f"#/experiments/{experiment}/runs/{run_id}" in direct.url
            chromium.close()
    finally:
        os.killpg(ui.pid, 15)
        ui.wait(timeout=30)
