"""`bash scripts/mlflow_ui.sh`: MLflow's UI on the project's store, at a URL that opens the training runs
(MLflow 3 starts on its GenAI view otherwise)."""

import os
import shutil
import socket
import subprocess
import time
import urllib.request

import pytest
from mlflow.tracking import MlflowClient

from tests.conftest import ROOT

SCRIPT = str(ROOT / "scripts" / "mlflow_ui.sh")


def _url(line: str) -> str:
    return line.split("open ", 1)[1].strip()


def test_the_script_prints_the_training_runs_url_for_its_store_and_port(tmp_path):
    env = {**os.environ, "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path}/m.db"}
    command = ["bash", SCRIPT, "--port", "5123", "--help"]
    out = subprocess.run(command, capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    first, *rest = out.stdout.splitlines()
    assert f"sqlite:///{tmp_path}/m.db" in first
    assert _url(first) == "http://127.0.0.1:5123/#/experiments?workflowType=machine_learning"
    assert any("--backend-store-uri" in line for line in rest)  # the rest is mlflow ui's own help


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_the_printed_url_opens_the_runs_where_the_plain_one_opens_genai(tmp_path, browser):
    from playwright.sync_api import sync_playwright

    uri = f"sqlite:///{tmp_path}/m.db"
    client = MlflowClient(uri)
    experiment = client.create_experiment("nrbench-denoise", artifact_location=(tmp_path / "art").as_uri())
    client.set_terminated(client.create_run(experiment, run_name="kpcn-cpu").info.run_id)
    port = _free_port()
    env = {**os.environ, "MLFLOW_TRACKING_URI": uri}
    ui = subprocess.Popen(["bash", SCRIPT, "--port", str(port)], stdout=subprocess.PIPE, text=True, env=env)
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
        with sync_playwright() as p:
            chromium = p.chromium.launch(executable_path=shutil.which("chromium"))
            page = chromium.new_page()
            page.goto(url.replace("#/experiments?", f"#/experiments/{experiment}?"))
            page.get_by_text("kpcn-cpu").wait_for(timeout=30_000)  # the runs table
            page.goto(f"http://127.0.0.1:{port}/#/experiments/{experiment}")
            # MLflow's default: the GenAI overview (its Usage / Quality / Tool calls tabs), no runs table
            page.get_by_text("Tool calls", exact=True).wait_for(timeout=30_000)
            assert page.get_by_text("kpcn-cpu").count() == 0
            chromium.close()
    finally:
        ui.terminate()
        ui.wait(timeout=30)
