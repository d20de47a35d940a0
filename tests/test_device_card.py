"""What every run and timing says it ran on: the device's name (a GPU's, or the CPU's model, never
blank), the threads, and the precision stated as PyTorch runs it (TF32 convolutions on recent GPUs)."""

from __future__ import annotations

import torch
from mlflow.tracking import MlflowClient

from src.train import device as device_module
from src.train.device import FP32_TF32_CONV, cpu_model, device_card, precision


def _gpu(monkeypatch, capability, conv, matmul):
    """Answer as a CUDA machine would (no GPU needed): its compute capability and TF32 flags."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_capability", lambda _=None: capability)
    monkeypatch.setattr(device_module, "tf32_flags", lambda: (conv, matmul))


def test_fp32_on_a_recent_gpu_says_its_convolutions_run_in_tf32(monkeypatch):
    cuda, cpu = torch.device("cuda"), torch.device("cpu")
    _gpu(monkeypatch, (8, 0), conv=True, matmul=False)  # PyTorch's defaults on an A100 / H100
    assert precision(False, cuda) == FP32_TF32_CONV == "fp32 (TF32 convolutions)"
    assert precision(True, cuda) == "bf16-autocast" and precision(False, cpu) == "fp32"
    _gpu(monkeypatch, (9, 0), conv=True, matmul=True)
    assert precision(False, cuda) == "fp32 (TF32 convolutions and matmuls)"
    _gpu(monkeypatch, (9, 0), conv=False, matmul=False)  # TF32 turned off: plain fp32
    assert precision(False, cuda) == "fp32"
    _gpu(monkeypatch, (7, 5), conv=True, matmul=True)  # before Ampere there is no TF32
    assert precision(False, cuda) == "fp32"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert precision(False, cuda) == "fp32"


def test_the_tf32_flags_are_pytorchs_own():
    from src.train.device import tf32_flags

    assert tf32_flags() == (torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32)


def test_the_cpu_is_named_by_its_model_and_never_blank(tmp_path, monkeypatch):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: X\nmodel name\t: Example CPU 9000 @ 3.0GHz\nflags\t: a b\n")
    assert cpu_model(str(info)) == "Example CPU 9000 @ 3.0GHz"
    info.write_text("processor\t: 0\nmodel name\t: \n")
    monkeypatch.setattr("platform.processor", lambda: "x86_64")
    assert cpu_model(str(info)) == "x86_64"
    monkeypatch.setattr("platform.processor", lambda: "")
    assert cpu_model(str(tmp_path / "absent")) == "unknown CPU"


def test_a_run_carries_the_device_card(tmp_path, monkeypatch):
    from src.run import _tracked_run
    from tests.conftest import smoke_config

    monkeypatch.setattr(device_module, "cpu_model", lambda cpuinfo="": "Example CPU 9000")
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    assert device_card(torch.device("cpu")) == {"device_name": "Example CPU 9000", "threads": "3"}
    cfg = smoke_config(tmp_path, tmp_path / "run", ["model=cross_bilateral", "device=cpu"])
    with _tracked_run(cfg, ["eval"]) as tracker:
        pass
    tags = MlflowClient(cfg.tracking.uri).get_run(tracker.run_id).data.tags
    assert (tags["nrbench.device_name"], tags["nrbench.threads"], tags["nrbench.precision"]) == (
        "Example CPU 9000",
        "3",
        "fp32",
    )


def test_a_report_says_what_its_timings_were_measured_on():
    """Each distinct device card with its run count; a run from before the card says what is missing."""
    import pandas as pd

    from src.report.tables import measured_on

    card = {
        "tags.nrbench.device_name": "AMD EPYC",
        "tags.nrbench.threads": "2",
        "tags.nrbench.precision": "fp32",
    }
    gpu = {**card, "tags.nrbench.device_name": "NVIDIA H100", "tags.nrbench.precision": FP32_TF32_CONV}
    old = {"tags.nrbench.device": "cpu", "tags.nrbench.precision": "fp32"}
    runs = pd.DataFrame([card, card, gpu, old])
    assert measured_on(runs) == (
        "AMD EPYC, 2 threads, fp32 (2 runs); NVIDIA H100, 2 threads, fp32 (TF32 convolutions) (1 run); "
        "cpu, model and threads not recorded, fp32 (1 run)"
    )
    assert measured_on(pd.DataFrame([{"tags.nrbench.profile": "cpu"}])) == (
        "device, model and threads not recorded (1 run)"
    )
    assert measured_on(pd.DataFrame()) == "no runs"
