"""The NeRF task end to end in the smoke profile: render the scenes, train each model, evaluate on the
test views, resume exactly, and report per scene."""

import json
import signal
import subprocess
import time

import numpy as np
import pandas as pd
import pytest
import torch
from mlflow.tracking import MlflowClient
from PIL import Image

from src.errors import DataError
from src.report.build import build_report
from src.stages import evaluate, render, train
from src.tracking.mlflow_tracking import job_run
from src.train.checkpoint import load_checkpoint
from src.train.nerf_trainer import NerfTrainer, train_nerf
from tests.conftest import (
    ROOT,
    assert_same_curves,
    cli_job,
    is_timed,
    one_line_error,
    smoke_config,
    stop_at,
)


def _cfg(data, run_dir, *overrides):
    return smoke_config(data, run_dir, ["task=nerf", *overrides])


@pytest.fixture(scope="module")
def nerf_data(tmp_path_factory, mitsuba_variant):
    data = tmp_path_factory.mktemp("nerf_data")
    render(_cfg(data, data / "run"))
    return data


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """Tiny tensors: two threads only add synchronisation cost on a 2-core machine."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="module")
def trained(nerf_data, tmp_path_factory):
    """Each model trained and evaluated on `spheres`, plus NeRF on `busy`: {(model, scene): run dir}."""
    runs = {}
    for model, scene in (
        ("nerf", "spheres"),
        ("mipnerf", "spheres"),
        ("refnerf", "spheres"),
        ("nerf", "busy"),
    ):
        run_dir = tmp_path_factory.mktemp(f"{model}-{scene}")
        cfg = _cfg(nerf_data, run_dir, f"model={model}", f"task.scene={scene}")
        with job_run(cfg, run_name=model, tags={"nrbench.model": model}) as tracker:
            train(cfg, tracker)
            evaluate(cfg, tracker)
        runs[(model, scene)] = run_dir
    return runs


@pytest.mark.parametrize("model", ["nerf", "mipnerf", "refnerf"])
def test_training_lowers_the_loss_and_renders_finite_test_views(trained, model):
    run_dir = trained[(model, "spheres")]
    curves = pd.read_csv(run_dir / "curves.csv")
    assert list(curves["step"]) == [0, 10, 20, 30]  # from the initialisation
    assert curves["val_loss_fine"].iloc[-1] < curves["val_loss_fine"].iloc[0]
    metrics = json.loads((run_dir / "eval" / "metrics.json").read_text())
    assert metrics["images"] == 2 and metrics["scene"] == "spheres"
    rows = pd.read_csv(run_dir / "eval" / "per_image.csv")
    assert list(rows["view"]) == ["spheres-r_0", "spheres-r_1"]
    for key in ("psnr", "ssim", "lpips", "mse", "ms_per_image", "rays_per_s"):
        assert np.isfinite(metrics["mean"][key]), key
        assert metrics["mean"][key] == pytest.approx(rows[key].mean(), rel=1e-12), key
    # metrics.tonemap is `clip` for NeRF and the render is clipped, so PSNR is -10 log10(MSE) per view.
    np.testing.assert_allclose(rows["psnr"], -10 * np.log10(rows["mse"]), rtol=1e-9)
    # The rays/s figure is the view's pixel count over its render time.
    np.testing.assert_allclose(rows["rays_per_s"], 24 * 16 / (rows["ms_per_image"] / 1e3), rtol=1e-9)
    # The cost card: the MLP FLOPs per ray (src/models/nerf/summary.py, tested there) at those rays/s.
    assert metrics["flops_per_ray"] > 1000
    np.testing.assert_allclose(rows["gflops"], metrics["flops_per_ray"] * rows["rays_per_s"] / 1e9, rtol=1e-9)
    # the training's clock beside each validation point
    assert curves["train_time_s"].iloc[0] == 0 and curves["train_time_s"].is_monotonic_increasing
    pngs = {p.name for p in (run_dir / "eval" / "png").iterdir()}
    assert {"spheres-r_0-rendered.png", "spheres-r_0-reference.png"} <= pngs
    # Scored on 8-bit images (task.eval.quantize_metrics, as multinerf and the thesis): exactly the PSNR
    # of the saved rendered and reference PNGs.
    for i, view in enumerate(rows["view"]):
        rendered, reference = (
            np.asarray(Image.open(run_dir / "eval" / "png" / f"{view}-{kind}.png"), dtype=np.float64) / 255
            for kind in ("rendered", "reference")
        )
        png_psnr = -10 * np.log10(np.mean((rendered - reference) ** 2))
        assert rows["psnr"][i] == pytest.approx(png_psnr, rel=1e-6), view
    buffers = {p.name for p in (run_dir / "eval" / "buffers").iterdir()}
    assert "spheres-r_0-depth.png" in buffers
    assert ("spheres-r_0-normals.png" in buffers) == (model == "refnerf")


def test_report_has_one_column_group_per_scene(trained, nerf_data, tmp_path):
    cfg = _cfg(nerf_data, tmp_path, f"report.out_dir={tmp_path}/reports")
    summary = build_report(cfg)
    assert summary["runs"] == 4 and not summary["warnings"]
    table = pd.read_csv(tmp_path / "reports" / "nerf" / "comparison.csv", comment="#", index_col=0)
    assert {"PSNR spheres", "PSNR busy", "SSIM spheres"} <= set(table.columns)
    assert set(table.index) == {"nerf", "mipnerf", "refnerf"}
    assert np.isnan(table.loc["mipnerf", "PSNR busy"])
    # Every filled cell is that (model, scene) run's own eval mean: a swapped scene or model would differ.
    for (model, scene), run_dir in trained.items():
        means = json.loads((run_dir / "eval" / "metrics.json").read_text())["mean"]
        for column, key in (
            ("PSNR", "psnr"),
            ("SSIM", "ssim"),
            ("relMSE (Bako)", "relmse"),
            ("FLIP", "flip"),
        ):
            cell = table.loc[model, f"{column} {scene}"]  # the CSV keeps 10 significant digits
            assert cell == pytest.approx(means[key], rel=1e-8), (model, scene, column)
    assert (tmp_path / "reports" / "nerf" / "image_grid.png").is_file()


def _uninterrupted(nerf_data, run_dir, common):
    cfg = _cfg(nerf_data, run_dir, *common)
    with job_run(cfg, run_name="a", tags={}) as tracker:
        reference = NerfTrainer(cfg, tracker)
        reference.fit()
    return reference


def _resume_and_compare(nerf_data, tmp_path, common, reference):
    """Resume the run in `tmp_path/b` into `tmp_path/c`: the same steps, weights and curves as `reference`
    (trained in `tmp_path/a`)."""
    resumed = _cfg(nerf_data, tmp_path / "c", *common, f"task.train.resume={tmp_path}/b/checkpoints")
    with job_run(resumed, run_name="c", tags={}) as tracker:
        summary = train_nerf(resumed, tracker)
    assert summary["steps"] == reference.pos.step
    final = load_checkpoint(summary["checkpoint"])["model"]
    for key, value in reference.model.state_dict().items():
        assert torch.equal(final[key], value), key
    assert_same_curves(tmp_path / "c" / "curves.csv", tmp_path / "a" / "curves.csv")


def test_resume_after_an_interrupt_matches_an_uninterrupted_run(nerf_data, tmp_path):
    common = ["model=mipnerf", "task.train.max_steps=12", "tracking.enabled=false"]
    reference = _uninterrupted(nerf_data, tmp_path / "a", common)
    interrupted = _cfg(nerf_data, tmp_path / "b", *common)
    with job_run(interrupted, run_name="b", tags={}) as tracker, pytest.raises(KeyboardInterrupt):
        train_nerf(interrupted, tracker, on_step=stop_at(7))  # Ctrl-C: the handler checkpoints step 7
    assert load_checkpoint(tmp_path / "b" / "checkpoints")["step"] == 7
    _resume_and_compare(nerf_data, tmp_path, common, reference)


def test_resume_with_single_image_batches_and_micro_batches_matches(nerf_data, tmp_path):
    """Issue 15 items 9a and 10a: one training view per step and gradient accumulation over micro-batches
    (the last one shorter) keep a resumed run identical to an uninterrupted one."""
    common = [
        "model=refnerf",
        "task.train.max_steps=6",
        "task.train.batching=single_image",
        "task.train.micro_batch_rays=24",
        "tracking.enabled=false",
    ]
    reference = _uninterrupted(nerf_data, tmp_path / "a", common)
    interrupted = _cfg(nerf_data, tmp_path / "b", *common)
    with job_run(interrupted, run_name="b", tags={}) as tracker, pytest.raises(KeyboardInterrupt):
        train_nerf(interrupted, tracker, on_step=stop_at(4))
    _resume_and_compare(nerf_data, tmp_path, common, reference)


def test_resume_after_a_crash_continues_from_the_periodic_checkpoint(nerf_data, tmp_path):
    """A crash no handler sees (SIGKILL, OOM; here an exception the loop does not catch) after step 13
    leaves the periodic checkpoint of step 10; resuming from it replays steps 11-14 exactly."""
    common = ["model=nerf", "task.train.max_steps=14", "tracking.enabled=false"]
    reference = _uninterrupted(nerf_data, tmp_path / "a", common)

    def crash(step):
        if step == 13:
            raise SystemError("simulated crash")

    interrupted = _cfg(nerf_data, tmp_path / "b", *common)
    with job_run(interrupted, run_name="b", tags={}) as tracker, pytest.raises(SystemError):
        train_nerf(interrupted, tracker, on_step=crash)
    assert load_checkpoint(tmp_path / "b" / "checkpoints")["step"] == 10
    _resume_and_compare(nerf_data, tmp_path, common, reference)


def _job(args, data, store, **popen):
    """`python -m src.run task=nerf profile=smoke *args` on the scenes in `data`, MLflow in `store`."""
    cmd, env = cli_job(["task=nerf", "profile=smoke", *args], data, store)
    return subprocess.Popen(cmd, cwd=ROOT, env=env, text=True, **popen)


@pytest.mark.slow
def test_a_run_killed_with_sigkill_resumes_to_the_same_weights_and_metrics(nerf_data, tmp_path):
    """The real CLI, killed with SIGKILL (no handler runs) once a periodic checkpoint past the first
    exists, then resumed from it in its run dir: the same final weights, curves, MLflow history (one
    point per step) and test metrics as an uninterrupted run."""
    common = ["task.train.max_steps=50", "task.train.checkpoint_every=5", "task.train.log_every=1"]

    def train_and_eval(name, *extra):
        for stage in ("train", "eval"):
            args = [f"stage={stage}", f"hydra.run.dir={tmp_path}/{name}", *common, *extra]
            job = _job(args, nerf_data, tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
            out, err = job.communicate(timeout=600)
            assert job.returncode == 0, out[-3000:] + err[-3000:]

    train_and_eval("a")
    args = ["stage=train", f"hydra.run.dir={tmp_path}/b", *common]
    job = _job(args, nerf_data, tmp_path, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    last = tmp_path / "b" / "checkpoints" / "last.pt"
    client = MlflowClient(f"sqlite:///{tmp_path}/mlflow.db")

    def logged_past_a_checkpoint():
        """A periodic checkpoint past the first exists and the job has logged steps after it (which
        the resumed job replays)."""
        if not last.exists():  # written atomically: a file there is whole
            return False
        state = load_checkpoint(last)
        logged = [m.step for m in client.get_metric_history(state["mlflow_run_id"], "train_psnr")]
        return state["step"] >= 10 and max(logged) > state["step"] + 1

    deadline = time.monotonic() + 300
    while not logged_past_a_checkpoint():
        assert job.poll() is None and time.monotonic() < deadline, "the job ended before it was killed"
        time.sleep(0.05)
    job.send_signal(signal.SIGKILL)
    job.wait()
    killed_at = load_checkpoint(last)
    assert not (tmp_path / "b" / "checkpoints" / "final.pt").exists()  # killed mid-training
    train_and_eval("b", f"task.train.resume={last.parent}")

    a, b = (load_checkpoint(tmp_path / n / "checkpoints" / "final.pt") for n in ("a", "b"))
    assert a["step"] == b["step"] == 50 and killed_at["step"] < 50
    for key, value in a["model"].items():
        assert torch.equal(b["model"][key], value), key
    assert_same_curves(tmp_path / "b" / "curves.csv", tmp_path / "a" / "curves.csv")

    means = [json.loads((tmp_path / n / "eval" / "metrics.json").read_text())["mean"] for n in ("a", "b")]
    assert {k: v for k, v in means[1].items() if not is_timed(k)} == {
        k: v for k, v in means[0].items() if not is_timed(k)
    }

    # The killed run was continued, not restarted, and holds what the uninterrupted one holds.
    assert b["mlflow_run_id"] == killed_at["mlflow_run_id"]
    runs = [client.get_run(c["mlflow_run_id"]) for c in (a, b)]
    assert [r.info.status for r in runs] == ["FINISHED", "FINISHED"]
    assert runs[1].data.metrics.keys() == runs[0].data.metrics.keys()
    for key in filter(lambda k: not is_timed(k), runs[0].data.metrics):
        history = [[(m.step, m.value) for m in client.get_metric_history(r.info.run_id, key)] for r in runs]
        assert sorted(history[1]) == sorted(history[0]), key


def test_the_rng_states_of_a_checkpoint_restore_every_seeded_generator():
    """What `seed_everything` seeds, a checkpoint restores: torch's CPU and CUDA generators (NeRF's
    sample jitter draws on the training device) and Python's."""
    import random

    from src.train.checkpoint import rng_states, set_rng_states

    def draws():
        cuda = torch.rand(3, device="cuda").cpu() if torch.cuda.is_available() else None
        return torch.rand(3), cuda, random.random()

    saved = rng_states()
    first = draws()
    set_rng_states(saved)
    again = draws()
    assert torch.equal(first[0], again[0]) and first[2] == again[2]
    assert first[1] is None or torch.equal(first[1], again[1])


def test_a_missing_scene_is_one_clear_line(nerf_data, tmp_path):
    cfg = _cfg(nerf_data, tmp_path, "task.scene=lego", "tracking.enabled=false")
    with job_run(cfg, run_name="x", tags={}) as tracker, pytest.raises(DataError) as excinfo:
        train(cfg, tracker)
    one_line_error(excinfo, "lego", "transforms_train.json")


def test_log_linear_schedule_closed_form():
    from src.train.schedules import log_linear_lr

    assert log_linear_lr(0, 5e-4, 5e-6, 1000) == pytest.approx(5e-4)
    assert log_linear_lr(500, 5e-4, 5e-6, 1000) == pytest.approx(5e-5)  # geometric mean halfway
    assert log_linear_lr(1000, 5e-4, 5e-6, 1000) == pytest.approx(5e-6)
    assert log_linear_lr(5000, 5e-4, 5e-6, 1000) == pytest.approx(5e-6)  # clipped after the end
    # warm-up: delay_mult at step 0, sin(pi/4) of the way at half the delay, no effect after it
    assert log_linear_lr(0, 1e-3, 1e-3, 100, 10, 0.01) == pytest.approx(1e-5)
    half = 0.01 + 0.99 * np.sin(np.pi / 4)
    assert log_linear_lr(5, 1e-3, 1e-3, 100, 10, 0.01) == pytest.approx(1e-3 * half)
    assert log_linear_lr(10, 1e-3, 1e-3, 100, 10, 0.01) == pytest.approx(1e-3)
