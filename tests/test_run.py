"""The Hydra entry point: config composition per profile, and the main job end to end (smoke)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from src.errors import ConfigError
from src.schema.run import validate_run
from tests.conftest import compose_config, one_line_cli_error, one_line_error, smoke_config

ROOT = Path(__file__).resolve().parent.parent


def run(args, data_dir, cwd=ROOT):
    """`python -m src.run` with data, Hydra outputs and MLflow all under `data_dir`."""
    env = {
        **os.environ,
        "NRBENCH_DATA_DIR": str(data_dir),
        "MLFLOW_TRACKING_URI": f"sqlite:///{data_dir}/mlflow.db",
    }
    cmd = [
        sys.executable,
        "-m",
        "src.run",
        f"hydra.run.dir={data_dir}/hydra",
        *args,
        f"tracking.artifact_root={data_dir}/mlartifacts",
        f"report.out_dir={data_dir}/reports",
    ]
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize(
    ("profile", "size", "reference_spp", "patch"),
    [("smoke", (48, 32), 128, 8), ("cpu", (128, 128), 1024, 32), ("paper", (1280, 720), 8192, 65)],
)
def test_profiles_compose(profile, size, reference_spp, patch):
    cfg = compose_config([f"profile={profile}"])
    assert (cfg.dataset.width, cfg.dataset.height) == size
    assert cfg.dataset.reference_spp == reference_spp and cfg.task.preprocess.patch_size == patch
    assert max(cfg.dataset.noisy_spp) < cfg.dataset.reference_spp


def test_default_profile_is_cpu_and_paper_is_the_thesis_set_up(tmp_path):
    """Bunjevac 2019, Sec. 4.1 and 6: 1280x720 at 128-1024 spp (8192 reference), 65x65 patches, 16,867 of
    them split 80/20, batch 64, 40 epochs (DPCN 80), fp32. `bako` keeps Bako et al.'s 1500 scenes."""
    assert compose_config().profile_name == "cpu"
    paper = compose_config(["profile=paper"])
    assert list(paper.dataset.noisy_spp) == [128, 256, 512, 1024]
    assert dict(paper.dataset.preprocess.patches_per_split) == {"train": 13494, "val": 3373}
    assert 13494 + 3373 == 16867 and round(0.8 * 16867) == 13494
    split = paper.task.preprocess.split
    assert split.train / (split.train + split.val) == pytest.approx(0.8)
    assert (paper.task.train.batch_size, paper.task.train.amp) == (64, False)
    epochs = {
        m: compose_config(["profile=paper", f"model={m}"]).task.train.epochs for m in ("kpcn", "resnet")
    }
    assert epochs == {"kpcn": 40, "resnet": 40}
    assert compose_config(["profile=paper", "model=dpcn"]).task.train.epochs == 80
    bako = compose_config(["profile=bako"])
    assert bako.dataset.scenes_per_base * len(bako.dataset.bases) == 1500
    assert (bako.dataset.preprocess.patches_per_image, bako.dataset.preprocess.patches_per_split) == (
        400,
        None,
    )
    assert (bako.dataset.width, bako.task.preprocess.patch_size, bako.task.train.epochs) == (1280, 65, 100)
    with pytest.raises(ConfigError) as excinfo:
        validate_run(smoke_config(tmp_path, tmp_path / "run", ["profile=bako", "task=nerf"]))
    one_line_error(excinfo, "profile=bako: has sizes for task ['denoise'], not task=nerf")


@pytest.fixture(scope="module")
def smoke_run(tmp_path_factory):
    data = tmp_path_factory.mktemp("data")
    result = run(["profile=smoke"], data)
    assert result.returncode == 0, result.stdout + result.stderr
    return data, result


def test_main_job_renders_and_preprocesses(smoke_run):
    data, result = smoke_run
    assert "samples/s" in result.stdout
    raw = data / "procedural" / "smoke" / "raw"
    assert len(list(raw.glob("*.exr"))) == 9  # 3 scenes x (2 noisy + 1 reference)
    render = json.loads((data / "procedural" / "smoke" / "render_summary.json").read_text())
    assert render["summary"]["samples_per_second"] > 0
    assert render["config"]["dataset"]["width"] == 48 and render["git_commit"]
    assert len(render["data_fingerprint"]) == 16
    prepared = data / "procedural" / "smoke" / "prepared"
    splits = json.loads((prepared / "splits.json").read_text())
    scenes = [s for names in splits.values() for s in names]
    assert len(scenes) == len(set(scenes)) == 3
    assert (prepared / "preprocess_provenance.json").exists()
    # ... then trains, evaluates and reports (the default model).
    assert "train: kpcn" in result.stdout and "eval: kpcn" in result.stdout
    assert (data / "reports" / "denoise" / "index.html").is_file()


def _stat(folder):
    return {p.name: (p.stat().st_mtime_ns, p.stat().st_size) for p in folder.iterdir()}


def test_rerun_renders_nothing(smoke_run):
    data, _ = smoke_run
    raw = data / "procedural" / "smoke" / "raw"
    before = _stat(raw)
    result = run(["profile=smoke", "stage=render"], data)
    assert result.returncode == 0 and "up to date" in result.stdout
    assert _stat(raw) == before  # not one EXR (or the manifest) rewritten


def test_unknown_stage_is_one_clear_line(tmp_path):
    result = run(["profile=smoke", "stage=train_everything"], tmp_path)
    one_line_cli_error(result, "stage", "train_everything")


def test_bad_exr_stops_preprocess_naming_the_file(smoke_run, tmp_path):
    from src.data.kpcn_buffers import load_kpcn_exr, write_kpcn_exr

    data, _ = smoke_run
    raw = tmp_path / "procedural" / "smoke" / "raw"
    raw.mkdir(parents=True)
    for exr in (data / "procedural" / "smoke" / "raw").glob("*.exr"):
        (raw / exr.name).write_bytes(exr.read_bytes())
    victim = raw / "cornell-0000-00004spp.exr"
    buffers, _ = load_kpcn_exr(victim)
    buffers["specular"][3, 5, 1] = np.nan
    write_kpcn_exr(victim, buffers)
    result = run(["profile=smoke", "stage=preprocess"], tmp_path)
    one_line_cli_error(result, str(victim), "specular.G", "task.preprocess.repair.nonfinite=zero")
    # Nothing half-written is left for a later stage to trust; the inputs are untouched.
    assert sorted(p.name for p in (tmp_path / "procedural" / "smoke").iterdir()) == ["raw"]
    assert len(list(raw.glob("*.exr"))) == 9
    repaired = run(["profile=smoke", "stage=preprocess", "task.preprocess.repair.nonfinite=zero"], tmp_path)
    assert repaired.returncode == 0, repaired.stderr
    prepared = tmp_path / "procedural" / "smoke" / "prepared"
    record = json.loads((prepared / "preprocess_provenance.json").read_text())
    assert "specular.G" in record["summary"]["repairs"]["cornell-0000-00004spp.exr"]
