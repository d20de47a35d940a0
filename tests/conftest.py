import os
import shutil
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

CONF_DIR = str(Path(__file__).resolve().parent.parent / "conf")

# The test files that run whole studies, longest first (20 s to 2.5 min each on a 2-core CPU).
# `scripts/test.sh` runs the suite on two xdist workers, each taking whole files in collection order
# (`--dist loadfile`): a long file collected last (alphabetical order puts test_sweeps.py near the end)
# would leave one worker alone for its last minutes, so these are collected first. Serial runs only see
# another file order.
LONGEST_FILES = (
    "test_sweeps.py",
    "test_cluster.py",
    "test_run.py",
    "test_denoise_train.py",
    "test_dvc_stages.py",
    "test_ladder.py",
)


def pytest_collection_modifyitems(config, items):
    rank = {name: i for i, name in enumerate(LONGEST_FILES)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: the rest keep their order


@pytest.fixture(scope="session")
def mitsuba_variant():
    """Activates the Mitsuba variant this machine supports (llvm_ad_rgb on CI) once per session."""
    from src.render.backend import set_mitsuba_variant

    return set_mitsuba_variant("auto")


@pytest.fixture(scope="module")
def single_thread():
    """One intra-op thread for a module of tiny-tensor tests (`pytestmark = pytest.mark.usefixtures(
    "single_thread")`): there threads cost more than they gain, e.g. on a busy 2-core machine a smoke NeRF
    training step took 0.27 s with 2 threads and 0.018 s with 1. Restored afterwards."""
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def compose_config(overrides=()):
    """The resolved-at-access root config, composed in-process as ``python -m src.run`` would. Without a
    Hydra run, `paths.root` (the run's working directory) has no value: a stand-in is set unless the
    overrides set it, so that what interpolates the paths (`dataset.feature_selection.dir`, which a data
    kind's options hold) resolves; nothing is written there."""
    overrides = list(overrides)
    if not any(o.split("=", 1)[0].lstrip("+") == "paths.root" for o in overrides):
        overrides.append("paths.root=/nrbench-compose")
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose(config_name="config", overrides=overrides, return_hydra_config=False)


def data_kind(cfg):
    """The run's data kind, built as a job builds it (`Task.for_run`)."""
    from src.stages import task_of

    return task_of(cfg).kind


def one_line_error(excinfo, *needles):
    """The raised message is one line and names every needle (file, channel, key...); returns it."""
    msg = str(excinfo.value)
    assert "\n" not in msg
    for needle in needles:
        assert needle in msg, (needle, msg)
    return msg


def one_line_cli_error(result, *needles):
    """A `python -m src.run` that failed on bad input: exit status 2, no traceback, and exactly one
    ERROR line, naming every needle; returns that line."""
    output = result.stdout + result.stderr
    assert result.returncode == 2, output[-3000:]
    assert "Traceback" not in output, output[-3000:]
    errors = [line for line in output.splitlines() if "ERROR" in line]
    assert len(errors) == 1, errors
    for needle in needles:
        assert needle in errors[0], (needle, errors[0])
    return errors[0]


def assert_loads_from_legacy_checkpoint(cfg, legacy_cfg, path):
    """A model built from `cfg`, saved in a checkpoint that records the older `legacy_cfg` (a config from
    before `model._target_`), loads back into a fresh model of `cfg` with every weight equal."""
    import torch

    from src.models.instantiate import build_method
    from src.train.checkpoint import load_weights, save_checkpoint

    trained = build_method(cfg)
    state = {"model_config": legacy_cfg, "model": trained.state_dict(), "optimizer": {}}
    save_checkpoint(path, state | {"epoch": 1, "batch_in_epoch": 0, "step": 5})
    fresh = build_method(cfg)
    load_weights(fresh, cfg, path)
    for key, value in trained.state_dict().items():
        assert torch.equal(fresh.state_dict()[key], value), key


ROOT = Path(__file__).resolve().parent.parent


def cli_job(args, data_dir, store=None):
    """(command, environment) of `python -m src.run *args` with the datasets under `data_dir` and MLflow
    (database, artifacts) and reports under `store` (default `data_dir`): for `subprocess.run` or, to
    signal the job, `subprocess.Popen`."""
    store = store or data_dir
    env = {
        **os.environ,
        "NRBENCH_DATA_DIR": str(data_dir),
        "MLFLOW_TRACKING_URI": f"sqlite:///{store}/mlflow.db",
    }
    paths = [f"tracking.artifact_root={store}/mlartifacts", f"report.out_dir={store}/reports"]
    return [sys.executable, "-m", "src.run", *args, *paths], env


def stop_at(step):
    """A training `on_step` hook that interrupts (as Ctrl-C would) once `step` is done."""

    def on_step(current):
        if current == step:
            raise KeyboardInterrupt

    return on_step


def smoke_config(data_dir, run_dir, overrides=()):
    """The smoke-profile config with data, run outputs and MLflow under temporary directories
    (composed outside a Hydra app, so the `${hydra:...}` paths are given explicitly)."""
    return compose_config(
        [
            "profile=smoke",
            f"paths.root={ROOT}",
            f"paths.data={data_dir}",
            f"paths.run_dir={run_dir}",
            f"tracking.uri=sqlite:///{data_dir}/mlflow.db",
            f"tracking.artifact_root={data_dir}/mlartifacts",
            f"report.out_dir={data_dir}/reports",
            *overrides,
        ]
    )


@pytest.fixture(scope="module")
def vol_data(tmp_path_factory):
    """<data>/volumetric/smoke/{raw,prepared} of tests/test_volume_shards.py's four synthetic 4-frame
    scenes (2 train, 1 val, 1 test), preprocessed with 8x8 patches."""
    from tests.test_volume_shards import _preprocess, _raw  # lazy: a test module's helpers

    data = tmp_path_factory.mktemp("voldata")
    raw = _raw(data / "volumetric" / "smoke" / "raw")
    _preprocess(raw, data / "volumetric" / "smoke" / "prepared", patch_size=8)
    return data


@pytest.fixture(scope="session")
def smoke_data(tmp_path_factory, mitsuba_variant):
    """A rendered and preprocessed smoke dataset, shared by the training/evaluation tests."""
    from src.stages import preprocess, render

    data = tmp_path_factory.mktemp("smoke_data")
    cfg = smoke_config(data, data / "run")
    render(cfg)
    preprocess(cfg)
    return data


@pytest.fixture(scope="module")
def browser():
    """Skips without Chromium and playwright, except under CI=true, where the check must run."""
    missing = []
    if shutil.which("chromium") is None:
        missing.append("chromium (apt-get install chromium)")
    try:
        import playwright  # noqa: F401
    except ImportError:
        missing.append("the playwright package (uv sync)")
    if missing and os.environ.get("CI") == "true":
        pytest.fail(f"CI must run the browser check; missing {', '.join(missing)}")
    if missing:
        pytest.skip(f"missing {', '.join(missing)}")


def assert_same_curves(resumed, straight):
    """Two runs' curves.csv hold the same values but the training clock (`train_time_s`, which differs
    between any two runs); the resumed run's clock continues its checkpoint's (never falls back)."""
    import pandas as pd

    a, b = pd.read_csv(resumed), pd.read_csv(straight)
    assert a["train_time_s"].is_monotonic_increasing and b["train_time_s"].is_monotonic_increasing
    pd.testing.assert_frame_equal(a.drop(columns="train_time_s"), b.drop(columns="train_time_s"))


#: Parts of a metric's name that mark it as measured by a clock or a memory counter (times, rates, the
#: speed-up, achieved GFLOP/s and its fraction of peak, peak memory): they differ between any two runs.
TIMED_MARKS = ("time", "seconds", "per_s", "ms_per", "speedup", "gflops", "peak_")


def is_timed(key: str) -> bool:
    """Whether two runs of one configuration may log different values of metric `key` (`TIMED_MARKS`)."""
    return any(mark in key for mark in TIMED_MARKS)
