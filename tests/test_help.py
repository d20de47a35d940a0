"""`python -m src.run --help` prints nrbench's own help (conf/hydra/help/nrbench.yaml): the config groups
from conf/, every profile, and common commands that compose and validate."""

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.conftest import ROOT, smoke_config

HELP = Path(ROOT) / "conf" / "hydra" / "help" / "nrbench.yaml"


def _section(template: str, title: str) -> list[str]:
    """The non-empty lines under `== title ==` up to the next section."""
    lines = template.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith(f"== {title}"))
    body = []
    for line in lines[start + 1 :]:
        if line.startswith("=="):
            break
        if line.strip():
            body.append(line.strip())
    return body


def _common_commands() -> list[list[str]]:
    template = yaml.safe_load(HELP.read_text())["template"]
    commands = []
    for line in _section(template, "Common commands"):
        command = re.split(r"\s{2,}", line)[0]  # two spaces part the command from its comment
        words = shlex.split(command)
        assert words[:3] == ["python", "-m", "src.run"], line
        commands.append([w for w in words[3:] if w != "-m"])
    return commands


def test_help_is_nrbench_s_with_the_groups_from_conf_and_no_full_config():
    result = subprocess.run(
        [sys.executable, "-m", "src.run", "--help"], capture_output=True, text=True, cwd=ROOT, timeout=120
    )
    assert result.returncode == 0, result.stderr[-2000:]
    out = result.stdout
    assert out.startswith("nrbench:")
    assert "powered by Hydra" not in out  # not Hydra's generic header
    for group in sorted(p.name for p in (Path(ROOT) / "conf").iterdir() if p.is_dir() and p.name != "hydra"):
        options = sorted(f.stem for f in (Path(ROOT) / "conf" / group).glob("*.yaml"))
        assert f"{group}: {', '.join(options)}" in out, group
    assert "tracking:" not in out  # the whole config (hundreds of lines) is left to --cfg job
    assert len(out.splitlines()) < 80


def test_help_lists_every_profile_once():
    template = yaml.safe_load(HELP.read_text())["template"]
    listed = [line.split()[0] for line in _section(template, "Profiles")]
    assert sorted(listed) == sorted(f.stem for f in (Path(ROOT) / "conf" / "profile").glob("*.yaml"))


def test_help_names_every_stage():
    from src.stages import STAGES, STANDALONE

    template = yaml.safe_load(HELP.read_text())["template"]
    text = " ".join(_section(template, "Stages"))
    for stage in [*STAGES, *STANDALONE]:
        assert stage in text, stage


@pytest.mark.parametrize("overrides", _common_commands(), ids=" ".join)
def test_help_s_common_commands_compose_and_validate(tmp_path, overrides):
    from src.schema.run import validate_run

    cfg = smoke_config(tmp_path, tmp_path / "run", [o for o in overrides if o != "profile=smoke"])
    validate_run(cfg)


def test_help_has_six_common_commands():
    assert len(_common_commands()) == 6
