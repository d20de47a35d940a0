"""Your own scene (docs/extending.md, README "Add a method, a scene, your own data"): the documented
command, with the example scene the repository ships, composes, validates and renders; a dataset with
neither base scenes nor scene files is refused in one line."""

import json
import shlex
import subprocess
import time
from pathlib import Path

import pytest

from src.data.kpcn_buffers import KPCN_LAYOUT
from src.errors import ConfigError
from src.render.render_dataset import scene_sources
from src.schema.run import validate_run
from tests.conftest import ROOT, cli_job, one_line_cli_error, one_line_error, smoke_config

EXAMPLE = "examples/scenes/glossy_sphere.xml"
#: The documented command (README.md and docs/extending.md show it verbatim: checked below).
COMMAND = f"python -m src.run stage=render 'dataset.scene_files=[{EXAMPLE}]' dataset.bases=[]"


def overrides(command: str = COMMAND) -> list[str]:
    return shlex.split(command)[3:]


def test_the_documented_command_is_the_one_the_docs_show():
    for page in ("README.md", "docs/extending.md"):
        assert COMMAND in (ROOT / page).read_text(), page


def test_own_scene_alone_composes_and_validates(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)  # the scene file is relative to where the command runs
    cfg = smoke_config(tmp_path, tmp_path / "run", overrides())
    values = validate_run(cfg)
    assert values["dataset"]["bases"] == [] and values["dataset"]["scene_files"] == [EXAMPLE]
    (source,) = scene_sources(values["dataset"])
    assert source.name == "glossy-sphere" and source.path == Path(EXAMPLE) and source.base is None


def test_own_scene_beside_the_base_scenes_adds_one_scene(tmp_path, monkeypatch):
    monkeypatch.chdir(ROOT)
    cfg = smoke_config(tmp_path, tmp_path / "run", [f"dataset.scene_files=[{EXAMPLE}]"])
    values = validate_run(cfg)
    names = [s.name for s in scene_sources(values["dataset"])]
    assert names[-1] == "glossy-sphere" and len(names) == 1 + len(values["dataset"]["bases"]) * int(
        values["dataset"]["scenes_per_base"]
    )


def test_no_base_scenes_and_no_scene_files_is_one_line(tmp_path):
    cfg = smoke_config(tmp_path, tmp_path / "run", ["dataset.bases=[]"])
    with pytest.raises(ConfigError) as err:
        validate_run(cfg)
    one_line_error(err, "dataset.bases=[]", "non-empty list", "dataset.scene_files")


@pytest.mark.slow
def test_no_scenes_through_the_cli_exits_2(tmp_path):
    cmd, env = cli_job(["stage=render", "profile=smoke", "dataset.bases=[]"], tmp_path)
    result = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=120)
    one_line_cli_error(result, "dataset.bases=[]", "dataset.scene_files")


@pytest.mark.slow
def test_the_documented_command_renders_the_example_at_smoke(tmp_path):
    """The command itself, through the CLI at profile=smoke: one scene, each noisy count and the reference."""
    start = time.perf_counter()
    cmd, env = cli_job([*overrides(), "profile=smoke"], tmp_path)
    result = subprocess.run(cmd, env=env, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, (result.stdout + result.stderr)[-3000:]
    raw = tmp_path / "procedural" / "smoke" / "raw"
    manifest = json.loads((raw / "manifest.json").read_text())
    assert sorted(manifest) == [f"glossy-sphere-{spp:05d}spp.exr" for spp in (4, 16, 128)]
    for name in manifest:  # the loader the preprocessing uses: every channel present, finite, non-negative
        buffers, _ = KPCN_LAYOUT.load(raw / name, expected_size=(32, 48))
        hit = buffers["depth"][..., 0] > 0
        assert 0.2 < hit.mean() < 1 and buffers["color"].mean() > 0, name  # the floor and sphere, some sky
    print(f"rendered in {time.perf_counter() - start:.1f} s")
