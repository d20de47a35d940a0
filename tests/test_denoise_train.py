"""Training, resume, checkpoints, tiled evaluation and MLflow logging of the denoisers (smoke profile)."""

import json
import subprocess

import mlflow
import numpy as np
import pandas as pd
import pytest
import torch
from omegaconf import OmegaConf

from src.data.color_spaces import KpcnSplit
from src.data.denoise_dataset import FullImageDataset
from src.errors import ConfigError, DataError
from src.eval.denoise_eval import denoise_tiled, evaluate_denoiser
from src.io.exr import read_exr
from src.metrics.image import relmse
from src.models.instantiate import build_method
from src.objectives.terms import BranchLosses, component_losses, objective
from src.stages import evaluate, train
from src.tracking.mlflow_tracking import job_run
from src.train.checkpoint import checkpoint_run_id, load_checkpoint, save_checkpoint
from src.train.device import precision
from src.train.schedules import log_linear_lr
from src.train.trainer import DenoiserTrainer, train_denoiser
from tests.conftest import (
    ROOT,
    cli_job,
    compose_config,
    data_kind,
    one_line_cli_error,
    one_line_error,
    smoke_config,
    stop_at,
)


def _untracked(data, run_dir, *overrides):
    return smoke_config(data, run_dir, ["tracking.enabled=false", *overrides])


def test_training_lowers_the_loss_and_logs_a_finished_mlflow_run(smoke_data, tmp_path):
    cfg = smoke_config(smoke_data, tmp_path, ["model=kpcn", "task.train.epochs=6", "task.train.lr=3e-3"])
    with job_run(cfg, run_name="kpcn-test", tags={"nrbench.model": "kpcn"}) as tracker:
        train(cfg, tracker)
        evaluate(cfg, tracker)
        run_id = tracker.run_id
    mlflow.set_tracking_uri(cfg.tracking.uri)
    client = mlflow.MlflowClient()
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED"
    for key in (
        *(f"{split}_loss_{c}" for split in ("train", "val") for c in ("diffuse", "specular", "color")),
        "train_step_loss_diffuse",
        "train_time_s",
        "param_count",
        "eval_psnr",
        "eval_ssim",
        "eval_relmse",
        "eval_noisy_relmse",
        "eval_ms_per_mpixel",
        "eval_relmse_spp4",
        "eval_energy_spp4",
        "eval_noisy_energy",
    ):
        assert key in run.data.metrics, key
    logged = run.data.metrics
    assert logged["epochs"] == 6
    assert logged["train_time_per_epoch_s"] == pytest.approx(logged["train_time_s"] / 6, rel=1e-5)
    history = [m.value for m in client.get_metric_history(run_id, "train_loss_diffuse")]
    assert len(history) == 6 and history[-1] < history[0]
    curves = pd.read_csv(tmp_path / "curves.csv")  # the same per-epoch values, for DVC plots
    np.testing.assert_allclose(curves["train_loss_diffuse"], history, rtol=1e-6)
    assert list(curves["epoch"]) == [1, 2, 3, 4, 5, 6] and "val_loss_specular" in curves
    eval_dir = tmp_path / "eval"
    assert (eval_dir / "metrics.json").is_file() and (eval_dir / "per_image.csv").is_file()
    record = json.loads((eval_dir / "provenance.json").read_text())
    assert record["config"]["model"]["name"] == "kpcn" and record["git_commit"] and record["data_fingerprint"]
    assert (
        len(list((eval_dir / "images").glob("*.exr"))) == len(list((eval_dir / "strips").glob("*.png"))) > 0
    )
    _check_eval_values(cfg, eval_dir, run.data.metrics)


def _check_eval_values(cfg, eval_dir, logged):
    """The eval numbers are the denoised image's, averaged honestly: metrics.json's means are the means of
    per_image.csv, MLflow logged those means, the noisy input scores differently, and one image's relMSE
    recomputed from the written EXR and the prepared reference equals its row."""
    means = json.loads((eval_dir / "metrics.json").read_text())["mean"]
    rows = pd.read_csv(eval_dir / "per_image.csv")
    assert len(rows) == len(FullImageDataset(cfg.paths.prepared, "test")) > 1
    for key in (
        "psnr",
        "ssim",
        "relmse",
        "smape",
        "energy",
        "energy_error",
        "noisy_energy",
        "noisy_relmse",
        "ms_per_mpixel",
    ):
        assert means[key] == pytest.approx(rows[key].mean(), rel=1e-12), key
        assert logged[f"eval_{key}"] == pytest.approx(means[key], rel=1e-12), key
    assert (rows["relmse"] != rows["noisy_relmse"]).all() and (rows["psnr"] != rows["noisy_psnr"]).all()
    item = FullImageDataset(cfg.paths.prepared, "test")[0]
    name = f"{item['scene']}-{int(item['spp']):05d}spp"
    written = read_exr(eval_dir / "images" / f"{name}.exr", ["R", "G", "B"])
    denoised = np.stack([written[c] for c in "RGB"], axis=-1)
    reference = item["reference"].permute(1, 2, 0).numpy()
    row = rows[(rows["scene"] == item["scene"]) & (rows["spp"] == int(item["spp"]))].iloc[0]
    assert relmse(denoised, reference, cfg.metrics.relmse_eps) == pytest.approx(row["relmse"], rel=1e-6)
    assert denoised.mean() / reference.mean() == pytest.approx(row["energy"], rel=1e-6)
    assert abs(denoised.mean() / reference.mean() - 1) == pytest.approx(row["energy_error"], abs=1e-6)
    noisy = item["color"].permute(1, 2, 0).numpy()
    assert relmse(noisy, reference, cfg.metrics.relmse_eps) == pytest.approx(row["noisy_relmse"], rel=1e-6)
    # The GP thesis's convention (Eq. 3.5) on the same images: 1.5 spp times Bako's, and its fitness ratio.
    gp = 1.5 * row["spp"] * np.array([row["relmse"], row["noisy_relmse"]])
    np.testing.assert_allclose([row["relmse_spp"], row["noisy_relmse_spp"]], gp, rtol=1e-9)
    assert row["relmse_ratio"] == pytest.approx(row["relmse"] / row["noisy_relmse"], rel=1e-9)
    assert logged["eval_relmse_ratio"] == pytest.approx(rows["relmse_ratio"].mean(), rel=1e-12)


def test_resume_after_an_interrupt_matches_an_uninterrupted_run(smoke_data, tmp_path):
    straight = _untracked(smoke_data, tmp_path / "a", "model=resnet", "task.train.epochs=3")
    with job_run(straight, run_name="a", tags={}) as tracker:
        reference = DenoiserTrainer(straight, tracker, kind=data_kind(straight))
        reference.fit()
    steps_per_epoch = reference.pos.step // 3
    interrupted = _untracked(smoke_data, tmp_path / "b", "model=resnet", "task.train.epochs=3")
    with job_run(interrupted, run_name="b", tags={}) as tracker, pytest.raises(KeyboardInterrupt):
        inside_epoch_2 = stop_at(steps_per_epoch + 1)
        train_denoiser(interrupted, tracker, data_kind(interrupted), on_step=inside_epoch_2)
    resumed = _untracked(
        smoke_data,
        tmp_path / "c",
        "model=resnet",
        "task.train.epochs=3",
        f"task.train.resume={tmp_path}/b/checkpoints",
    )
    with job_run(resumed, run_name="c", tags={}) as tracker:
        summary = train_denoiser(resumed, tracker, data_kind(resumed))
    assert summary["steps"] == reference.pos.step
    # The resumed run's curves file continues the interrupted one's: all three epochs, in order.
    assert list(pd.read_csv(tmp_path / "c" / "curves.csv")["epoch"]) == [1, 2, 3]
    final = load_checkpoint(summary["checkpoint"])["model"]
    for key, value in reference.model.state_dict().items():
        assert torch.equal(final[key], value.cpu()), key


def test_the_run_id_of_a_checkpoint_is_read_without_its_weights(tmp_path, monkeypatch):
    """`checkpoint_run_id` (what src/run.py continues) asks torch to map the tensors instead of reading
    them, and gives the run id by value; a broken file is the same one line."""
    weights = {"w": torch.arange(1_000, dtype=torch.float32)}
    state = {
        "model_config": {},
        "model": weights,
        "optimizer": {},
        "epoch": 1,
        "batch_in_epoch": 0,
        "step": 9,
    }
    save_checkpoint(tmp_path / "run.pt", {**state, "mlflow_run_id": "abc123"})
    save_checkpoint(tmp_path / "untracked.pt", state)
    loads = []
    real_load = torch.load
    monkeypatch.setattr(torch, "load", lambda *a, **kw: loads.append(kw.get("mmap")) or real_load(*a, **kw))
    assert checkpoint_run_id(tmp_path / "run.pt") == "abc123"
    assert checkpoint_run_id(tmp_path / "untracked.pt") is None
    assert load_checkpoint(tmp_path / "run.pt", mmap=True)["model"]["w"][-1] == 999  # mapped, same values
    assert loads == [True, True, True]
    load_checkpoint(tmp_path / "run.pt")  # a training's resume reads everything
    assert loads[-1] is False
    (tmp_path / "broken.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(DataError) as err:
        checkpoint_run_id(tmp_path / "broken.pt")
    one_line_error(err, "broken.pt")


def test_malformed_or_mismatched_checkpoint_is_one_clear_line(smoke_data, tmp_path):
    garbage = tmp_path / "broken.pt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(DataError) as err:
        load_checkpoint(garbage)
    one_line_error(err, "broken.pt")
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(DataError) as err:
        load_checkpoint(foreign)
    one_line_error(err, "foreign.pt", "not an nrbench checkpoint")

    cfg = _untracked(smoke_data, tmp_path, "model=dpcn", f"task.eval.checkpoint={tmp_path}/kpcn.pt")
    kpcn_cfg = OmegaConf.to_container(_untracked(smoke_data, tmp_path, "model=kpcn").model, resolve=True)
    state = {
        "model_config": kpcn_cfg,
        "model": {},
        "optimizer": {},
        "epoch": 0,
        "batch_in_epoch": 0,
        "step": 0,
    }
    save_checkpoint(tmp_path / "kpcn.pt", state)
    with job_run(cfg, run_name="x", tags={}) as tracker, pytest.raises(DataError) as err:
        evaluate_denoiser(cfg, tracker, data_kind(cfg))
    one_line_error(err, "kpcn.pt", "model.output")


@pytest.mark.parametrize("model", ["kpcn", "resnet", "dpcn", "cross_bilateral"])
def test_tiled_inference_equals_a_full_frame_pass(smoke_data, model):
    cfg = _untracked(smoke_data, smoke_data / "run", f"model={model}")
    torch.manual_seed(0)
    denoiser = build_method(OmegaConf.to_container(cfg.model, resolve=True)).eval()
    item = FullImageDataset(cfg.paths.prepared, "test")[0]
    batch = {k: v[None] for k, v in item.items() if isinstance(v, torch.Tensor)}
    space = KpcnSplit(cfg.dataset.preprocess.eps_albedo)
    full = denoise_tiled(denoiser, batch, tile=10_000, space=space)
    tiled = denoise_tiled(denoiser, batch, tile=7, space=space)  # 48x32 in ragged 7x7 tiles
    torch.testing.assert_close(tiled, full, rtol=1e-5, atol=1e-6)


def _run_cli(args, data, cwd=ROOT):
    cmd, env = cli_job(args, data)
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)


def test_multirun_gives_one_parent_with_a_child_per_model_and_a_table(smoke_data, tmp_path):
    data = smoke_data.parent / "multirun_data"
    if not data.exists():
        data.symlink_to(smoke_data)
    sweep = tmp_path / "sweep"
    result = _run_cli(["-m", "profile=smoke", "model=kpcn,cross_bilateral", f"hydra.sweep.dir={sweep}"], data)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    mlflow.set_tracking_uri(f"sqlite:///{data}/mlflow.db")
    runs = mlflow.search_runs(
        experiment_names=["nrbench-denoise"], filter_string=f"tags.`nrbench.sweep_dir` = '{sweep}'"
    )
    parents = runs[runs["tags.mlflow.parentRunId"].isna()]
    children = runs[runs["tags.mlflow.parentRunId"].notna()]
    assert len(parents) == 1 and len(children) == 2
    assert set(children["tags.mlflow.parentRunId"]) == set(parents["run_id"])
    assert set(children["status"]) == {"FINISHED"}
    assert "kpcn" in result.stdout and "cross_bilateral" in result.stdout and "relMSE" in result.stdout
    # The sweep ends with one report over its children (not one per job).
    assert result.stdout.count("report: 2 runs -> ") == 1 and "report: 1 runs -> " not in result.stdout
    table = (data / "reports" / "denoise" / "comparison.md").read_text()
    assert "kpcn" in table and "cross_bilateral" in table and "**" in table
    assert (data / "reports" / "denoise" / "index.html").is_file()


def test_unknown_model_name_is_a_clear_error(tmp_path):
    result = _run_cli(["model=kpcnn", f"hydra.run.dir={tmp_path}/h"], tmp_path)
    one_line_cli_error(result, "model=kpcnn: no such model; did you mean kpcn")
    assert not (tmp_path / "h").exists()  # rejected before Hydra made the job's folder


def test_summary_stage_prints_parameters_without_training(tmp_path):
    result = _run_cli(
        ["stage=summary", "model=dpcn", "profile=paper", f"hydra.run.dir={tmp_path}/h"], tmp_path
    )
    assert result.returncode == 0, result.stderr
    assert "3,656,606" in result.stdout or "3656606" in result.stdout  # 2 branches x 1,828,303
    assert not (tmp_path / "mlflow.db").exists()


def test_a_model_trains_and_evaluates_on_the_features_configured(smoke_data, tmp_path):
    features = "task.features=[color,albedo,normal,visibility,visibility.grad]"
    cfg = _untracked(smoke_data, tmp_path, "model=dpcn", "model.whiten=true", "task.train.epochs=1", features)
    with job_run(cfg, run_name="x", tags={}) as tracker:
        summary = train_denoiser(cfg, tracker, data_kind(cfg))
        state = load_checkpoint(summary["checkpoint"])
        assert state["features"] == ["color", "albedo", "normal", "visibility", "visibility.grad"]
        assert state["model_config"]["in_channels"] == 12
        assert state["model"]["diffuse_mean"].numel() == 12  # whitening statistics of those channels
        assert evaluate_denoiser(cfg, tracker, data_kind(cfg))["images"] > 0
        features = "task.features=[color,normal,albedo,depth,depth.grad]"
        other = _untracked(smoke_data, tmp_path, "model=dpcn", "model.whiten=true", features)
        with pytest.raises(DataError) as err:
            evaluate_denoiser(other, tracker, data_kind(other))
    one_line_error(err, "final.pt", "task.features=[color,albedo,normal,visibility,visibility.grad]")


def test_a_bad_feature_list_is_one_line_before_anything_runs(tmp_path):
    result = _run_cli(["stage=summary", "model=kpcn", "task.features=[color,colour]"], tmp_path)
    one_line_cli_error(result, "task.features[1]='colour'", ".var or .grad")


class _Fixed(torch.nn.Module):
    """A stand-in model returning fixed outputs, to see which losses the trainer forms from them."""

    def __init__(self, outputs):
        super().__init__()
        self.outputs = outputs

    def forward(self, batch):
        return self.outputs


def test_the_objective_is_the_loss_of_what_the_model_predicts():
    ones, zeros = torch.ones(1, 3, 2, 2), torch.zeros(1, 3, 2, 2)
    batch = {"diffuse_target": zeros, "specular_target": zeros, "reference": zeros, "albedo": zeros}
    l1 = lambda out, target: (out - target).abs().mean()  # noqa: E731
    space = KpcnSplit(0.5)
    pair = component_losses(_Fixed({"diffuse": ones, "specular": 2 * ones}), batch, l1, space)
    assert list(pair) == ["diffuse", "specular", "color"]
    assert float(objective(pair)) == 3.0  # diffuse + specular; the rebuilt colour is only logged
    assert float(pair["color"]) == pytest.approx(0.5 + np.expm1(2.0))  # (albedo + eps) d + exp(s) - 1
    color = component_losses(_Fixed({"color": 4 * ones}), batch, l1, space)
    assert list(color) == ["color"] and float(objective(color)) == 4.0
    with pytest.raises(DataError) as err:
        component_losses(_Fixed({"colour": ones}), batch, l1, space)
    one_line_error(err, "_Fixed.forward", "'colour'", "'specular'")


def test_the_optimiser_and_the_loss_are_built_from_config(smoke_data, tmp_path):
    cfg = _untracked(
        smoke_data,
        tmp_path,
        "model=dpcn",
        "task.train.lr=0.02",
        "task.train.optimizer._target_=torch.optim.SGD",
        "+task.train.optimizer.momentum=0.5",
        "task.train.loss={_target_: src.objectives.losses.smape, eps: 0.5}",
    )
    with job_run(cfg, run_name="x", tags={}) as tracker:
        trainer = DenoiserTrainer(cfg, tracker, kind=data_kind(cfg))
    assert isinstance(trainer.optimizer, torch.optim.SGD)
    assert (
        trainer.optimizer.param_groups[0]["lr"] == 0.02
        and trainer.optimizer.param_groups[0]["momentum"] == 0.5
    )
    pred, target = torch.full((4,), 2.0), torch.ones(4)
    assert float(trainer.terms.loss(pred, target)) == pytest.approx(1 / 3.5)  # |2 - 1| / (2 + 1 + eps 0.5)

    bad = _untracked(smoke_data, tmp_path, "model=dpcn", "task.train.optimizer._target_=torch.optim.Adamm")
    with job_run(bad, run_name="x", tags={}) as tracker, pytest.raises(ConfigError) as err:
        DenoiserTrainer(bad, tracker, kind=data_kind(bad))
    one_line_error(err, "task.train.optimizer", "Adamm")  # a bad loss's lines: tests/test_losses.py


def test_a_learning_rate_schedule_from_config_sets_each_steps_rate(smoke_data, tmp_path):
    schedule = "{_target_: src.train.schedules.log_linear_lr, _partial_: true, lr_final: 1.0e-5}"
    cfg = _untracked(
        smoke_data,
        tmp_path,
        "model=dpcn",
        "task.train.lr=1e-3",
        "task.train.max_steps=2",
        f"task.train.schedule={schedule}",
    )
    seen = []
    with job_run(cfg, run_name="x", tags={}) as tracker:
        trainer = DenoiserTrainer(
            cfg,
            tracker,
            on_step=lambda step: seen.append(trainer.optimizer.param_groups[0]["lr"]),
            kind=data_kind(cfg),
        )
        trainer.fit()
    assert seen == [pytest.approx(log_linear_lr(s, 1e-3, 1e-5, 2)) for s in (0, 1)]  # decays over max_steps
    assert seen[1] == pytest.approx(1e-4)  # halfway: the geometric mean

    bad = _untracked(
        smoke_data, tmp_path, "model=dpcn", "task.train.schedule={_target_: src.train.schedules.nope}"
    )
    with job_run(bad, run_name="x", tags={}) as tracker, pytest.raises(ConfigError) as err:
        DenoiserTrainer(bad, tracker, kind=data_kind(bad))
    one_line_error(err, "task.train.schedule", "nope")


def test_precision_is_fp32_unless_amp_on_cuda(monkeypatch):
    """bf16 autocast is an opt-in for speed on CUDA (tagged nrbench.precision); the papers train fp32 (on a
    GPU without TF32 here: tests/test_device_card.py states TF32 where it applies)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    assert [precision(False, cuda), precision(True, cpu), precision(True, cuda)] == [
        "fp32",
        "fp32",
        "bf16-autocast",
    ]
    assert compose_config().task.train.amp is False


def test_the_denoiser_trainers_amp_step_runs_the_convolutions_in_bf16_and_the_loss_in_fp32(monkeypatch):
    """`task.train.amp` as on CUDA, taken on the CPU (`device.precision` patched to answer as for a CUDA
    device, so the trainer's own `_autocast` picks bfloat16): in `DenoiserTrainer.train_step` every
    convolution's output is the bf16 convolution of its bf16-rounded input and parameters (by value),
    the kernels' application and the losses stay fp32 (each logged loss the float64 L1 of the fp32
    predictions, to fp32 precision); with amp off every convolution runs in fp32."""
    from functools import partial
    from types import SimpleNamespace

    from src.models.denoise.summary import random_batch
    from src.train import device
    from tests.test_denoise_models import tiny_cfg

    monkeypatch.setattr(device, "precision", lambda amp, _: "bf16-autocast" if amp else "fp32")
    torch.manual_seed(0)
    model = build_method(tiny_cfg(whiten=False))
    batch = random_batch(8, 8, generator=torch.Generator().manual_seed(1))
    convs: list[tuple[torch.nn.Conv2d, torch.Tensor, torch.Tensor]] = []
    for m in model.modules():
        if isinstance(m, torch.nn.Conv2d):
            m.register_forward_hook(
                lambda m, args, out: convs.append((m, args[0].detach().clone(), out.detach().clone()))
            )
    seen: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = []

    def l1(prediction, target):
        loss = (prediction - target).abs().mean()
        seen.append((prediction.detach(), target, loss.detach()))
        return loss

    def step(amp):
        convs.clear(), seen.clear()
        trainer = SimpleNamespace(
            model=model,
            optimizer=torch.optim.SGD(model.parameters(), lr=0.0),
            t=OmegaConf.create({"amp": amp}),
            device=torch.device("cpu"),
            terms=BranchLosses(l1, KpcnSplit(0.01)),
            dropout=None,
        )
        trainer.losses = partial(DenoiserTrainer.losses, trainer)
        trainer.losses_of_frames = partial(DenoiserTrainer.losses_of_frames, trainer)
        trainer.objective = partial(DenoiserTrainer.objective, trainer)
        return DenoiserTrainer.train_step(trainer, {k: v[:, None] for k, v in batch.items()})  # one frame

    values, size = step(True)
    assert size == 1 and list(values) == ["diffuse", "specular", "color"] and len(seen) == 3
    assert len(convs) == 2 * 2  # per branch: depth 2 (a hidden and the kernel-logit convolution)
    for conv, x, out in convs:
        assert out.dtype == torch.bfloat16
        expected = conv._conv_forward(x.bfloat16(), conv.weight.bfloat16(), conv.bias.bfloat16())
        assert torch.equal(out, expected)
    for (prediction, target, loss), logged in zip(seen, values.values(), strict=True):
        assert prediction.dtype == loss.dtype == torch.float32
        assert logged == pytest.approx(float((prediction.double() - target.double()).abs().mean()), rel=1e-6)
    step(False)
    assert {out.dtype for _, _, out in convs} == {torch.float32}
