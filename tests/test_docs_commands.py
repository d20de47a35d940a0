"""Every `python -m src.run` command the README and docs/*.md show still composes (issue 34): a renamed or
removed config key, group or option in a documented command fails here instead of in a reader's shell.

The commands are extracted from fenced ```bash blocks (backslash continuations joined, comments dropped,
`VAR=value` prefixes and `;`/`&&` chains split) and from inline `code` spans, with `bash scripts/main.sh
<overrides>` read as the same Hydra job. Each is composed with Hydra's compose API exactly as the command
line would compose it (`-m` sweeps: every value of every swept key, each composed once with the other keys
at their first value; `+sweep=<study>` with its `hydra` section, as tests/test_sweeps.py does). Jobs are
not run. A placeholder in angle brackets (`<date>`, `<name>`) stands for any value and is replaced by a
stand-in (`PLACEHOLDERS`); paths such as `/data/nerf_synthetic` are plain strings to Hydra.
"""

from __future__ import annotations

import functools
import re
import shlex
from dataclasses import dataclass

import pytest
from hydra import compose, initialize_config_dir
from hydra.core.override_parser.overrides_parser import OverridesParser

from tests.conftest import CONF_DIR, ROOT

#: Pages whose commands are checked (docs/results/ holds generated snapshots, not commands to type).
PAGES = ["README.md", *sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "docs").glob("*.md"))]
#: Flags of `python -m src.run` that are not overrides (Hydra's own), with whether each takes a value.
FLAGS = {"-m": False, "--multirun": False, "--cfg": True, "-c": True, "--resolve": False, "--info": False}
#: A placeholder where a config group needs a real option -> the option composed in its place; any other
#: `<placeholder>` (`<date>`, `<sweep parent run id>`) becomes STAND_IN.
PLACEHOLDERS = {
    "model=<name>": "model=kpcn",
    "+sweep=<name>": "+sweep=whitening",
    "+sweep=X": "+sweep=whitening",
    "<from best_expressions.yaml>": "pi",  # an expression the search wrote: any that parses
}
STAND_IN = "placeholder"

_RUNNERS = (
    re.compile(r"^(?:\S*/)?python3? -m src\.run(?:\s|$)"),
    re.compile(r"^bash scripts/main\.sh(?:\s|$)"),
)


@dataclass(frozen=True)
class Command:
    page: str
    line: int
    text: str

    @property
    def where(self) -> str:
        return f"{self.page}:{self.line}: {self.text}"


def _fenced_bash(text: str) -> list[tuple[int, str]]:
    """(line number, command) of each ```bash block's commands: continuations joined, one per line."""
    found, block, start, joined = [], None, 0, ""
    for number, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if block is None:
            if stripped.startswith("```bash"):
                block = []
            continue
        if stripped.startswith("```"):
            block = None
            continue
        if not joined:
            start = number
        joined += line.rstrip()
        if joined.endswith("\\"):
            joined = joined[:-1] + " "
            continue
        found.append((start, joined.strip()))
        joined = ""
    return found


def _inline_spans(text: str) -> list[tuple[int, str]]:
    """(line number, text) of each inline `code` span outside fenced blocks (spans may wrap lines)."""
    lines, inside = [], False
    for line in text.splitlines():
        if line.strip().startswith("```"):
            inside = not inside
            lines.append("")
            continue
        lines.append("" if inside else line)
    flat = "\n".join(lines)
    return [
        (flat.count("\n", 0, m.start()) + 1, " ".join(m.group(1).split()))
        for m in re.finditer(r"(?<!`)`([^`]+)`(?!`)", flat)
    ]


def _simple_commands(line: str) -> list[str]:
    """A shell line's simple commands: split at `;`, `&&`, `||`, `|` outside quotes, comments dropped."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|")
    lexer.whitespace_split = True
    lexer.commenters = "#"
    commands, current = [], []
    try:
        tokens = list(lexer)
    except ValueError:  # an unclosed quote: not a shell line (prose in a code span)
        return []
    for token in tokens:
        if token and set(token) <= set(";&|"):
            commands.append(current)
            current = []
        else:
            current.append(token.replace("\\`", "`"))
    commands.append(current)
    out = []
    for words in commands:
        while words and re.match(r"^[A-Za-z_][A-Za-z0-9_]*=", words[0]):  # VAR=value prefixes
            words = words[1:]
        if words[:1] == ["time"]:
            words = words[1:]
        if words:
            out.append(shlex.join(words))
    return out


def documented_commands(pages=PAGES) -> list[Command]:
    """Every command of `pages` that runs the Hydra entry point."""
    commands = []
    for page in pages:
        text = (ROOT / page).read_text(encoding="utf-8")
        for number, line in _fenced_bash(text) + _inline_spans(text):
            for command in _simple_commands(line):
                if any(runner.match(command) for runner in _RUNNERS):
                    commands.append(Command(page, number, command))
    return commands


def hydra_args(command: str) -> tuple[bool, list[str]]:
    """(multirun, overrides) of one command. Placeholders are replaced first; a word with `...` (`+sweep=...`:
    any value) or without `=` (`[overrides]`: the syntax of a usage line, never an override) is dropped."""
    for placeholder, stand_in in PLACEHOLDERS.items():
        command = command.replace(placeholder, stand_in)
    words = shlex.split(re.sub(r"<[^<>]*>", STAND_IN, command))
    words = words[3:] if words[0].endswith(("python", "python3")) else words[2:]
    multirun, overrides = False, []
    skip = False
    for word in words:
        if skip:
            skip = False
        elif word in FLAGS:
            multirun |= word in ("-m", "--multirun")
            skip = FLAGS[word]
        elif "..." not in word and ("=" in word or word.startswith("~")):
            overrides.append(word)
    return multirun, overrides


def jobs(multirun: bool, overrides: list[str]) -> list[list[str]]:
    """The override lists to compose: the command's own, and with `-m` each value of each swept key once
    (the other swept keys at their first value)."""
    parsed = OverridesParser.create().parse_overrides(overrides)
    if not multirun or not any(o.is_sweep_override() for o in parsed):
        return [overrides]
    first = [
        f"{o.get_key_element()}={next(iter(o.sweep_string_iterator()))}" if o.is_sweep_override() else text
        for o, text in zip(parsed, overrides, strict=True)
    ]
    out = []
    for i, o in enumerate(parsed):
        if o.is_sweep_override():
            for value in o.sweep_string_iterator():
                out.append([*first[:i], f"{o.get_key_element()}={value}", *first[i + 1 :]])
    return out


def compose_job(overrides: list[str]):
    with initialize_config_dir(config_dir=CONF_DIR, version_base="1.3"):
        return compose("config", overrides=overrides, return_hydra_config=True)


@functools.cache
def _composes(overrides: tuple[str, ...]) -> str | None:
    """None if the job composes, else the error (cached: many pages show the same job)."""
    try:
        compose_job(list(overrides))
    except Exception as err:  # the test names the page, line and command with the message
        return f"{type(err).__name__}: {err}"
    return None


COMMANDS = documented_commands()


def test_the_docs_show_commands_of_every_system():
    """The extraction finds the documented commands at all (an extractor that finds nothing passes
    everything): the quickstart's four jobs among them, from fenced blocks and from inline spans."""
    texts = {c.text for c in COMMANDS}
    for quickstart in (
        "python -m src.run profile=smoke",
        "python -m src.run dataset=volumetric model=unet_kpcn profile=smoke",
        "python -m src.run task=filter_search profile=smoke",
        "python -m src.run task=nerf model=mipnerf task.scene=tabletop profile=smoke",
        "python -m src.run stage=ledger profile=smoke",
        "bash scripts/main.sh profile=smoke",  # an inline span
    ):
        assert quickstart in texts, quickstart
    assert len(COMMANDS) >= 80 and {c.page for c in COMMANDS} >= {"README.md", "docs/studies.md"}


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: f"{c.page}:{c.line}")
def test_documented_command_composes(command, monkeypatch):
    monkeypatch.chdir(ROOT)  # hydra.searchpath=[file://tests/conf] is relative to where a reader runs it
    multirun, overrides = hydra_args(command.text)
    for job in jobs(multirun, overrides):
        if error := _composes(tuple(job)):
            pytest.fail(f"{command.where}\n  composed as {job}\n  {error}")


@pytest.mark.parametrize(
    "line, expected",
    [
        ("python -m src.run a=1 b=2   # comment", ["python -m src.run a=1 b=2"]),
        (
            "MLFLOW_TRACKING_URI=sqlite:///x.db python -m src.run stage=ledger",
            ["python -m src.run stage=ledger"],
        ),
        ("git stash; python -m src.run a=1 && echo ok", ["git stash", "python -m src.run a=1", "echo ok"]),
        ("python -m src.run 'x=[a,b]' y=\"#1\"", ["python -m src.run 'x=[a,b]' 'y=#1'"]),
    ],
)
def test_shell_lines_split_into_commands(line, expected):
    assert _simple_commands(line) == expected


def test_blocks_spans_and_placeholders_are_read_as_a_reader_types_them(tmp_path):
    page = tmp_path / "page.md"
    page.write_text(
        "Run `python -m src.run\nmodel=dpcn` or `ls`.\n\n"
        "```bash\npython -m src.run -m model=kpcn,dpcn \\\n    task.train.lr=1e-4   # two jobs\n```\n"
        "```yaml\npython -m src.run not=bash\n```\n"
        "```bash\n.venv/bin/python -m src.run task.train.resume=outputs/<date>/<time>/x --cfg job\n```\n"
    )
    found = [(c.line, c.text) for c in documented_commands([page])]  # ROOT / an absolute path = the path
    assert found == [
        (5, "python -m src.run -m model=kpcn,dpcn task.train.lr=1e-4"),
        (12, ".venv/bin/python -m src.run 'task.train.resume=outputs/<date>/<time>/x' --cfg job"),
        (1, "python -m src.run model=dpcn"),
    ]
    assert hydra_args(found[1][1]) == (False, ["task.train.resume=outputs/placeholder/placeholder/x"])
    assert jobs(*hydra_args(found[0][1])) == [
        ["model=kpcn", "task.train.lr=1e-4"],
        ["model=dpcn", "task.train.lr=1e-4"],
    ]


@pytest.mark.slow
def test_documented_single_jobs_pass_the_job_start_checks(tmp_path, monkeypatch):
    """Beyond composing: each documented single job (no sweep, no launcher) passes the schema checks a job
    makes at start (`validate_run`: values, ranges, the method's constructor), as `dataset.bases=[]` with
    scene files once did not. ~20 s, so not in the default suite."""
    from src.schema.run import validate_run
    from tests.conftest import compose_config

    monkeypatch.chdir(ROOT)
    paths = [f"paths.root={ROOT}", f"paths.data={tmp_path}", f"paths.run_dir={tmp_path}/run"]
    failures = []
    for command in COMMANDS:
        multirun, overrides = hydra_args(command.text)
        if multirun or any(o.lstrip("+").startswith(("sweep=", "hydra")) for o in overrides):
            continue
        try:
            validate_run(compose_config([*paths, *overrides]))
        except Exception as err:  # collect every failing command with its message
            failures.append(f"{command.where}: {type(err).__name__}: {err}")
    assert not failures, "\n".join(failures)


def test_a_stale_key_in_a_documented_command_fails(monkeypatch):
    """The check bites: the quickstart's NeRF command with a key the config no longer has."""
    monkeypatch.chdir(ROOT)
    multirun, overrides = hydra_args("python -m src.run task=nerf task.scen=tabletop profile=smoke")
    (job,) = jobs(multirun, overrides)
    assert "task.scen" in (_composes(tuple(job)) or "")  # the path test_documented_command_composes takes
    assert _composes(("task=nerf", "task.scene=tabletop", "profile=smoke")) is None


def test_relative_links_between_pages_resolve():
    """Every relative link of README.md and docs/*.md names a file that exists (pages moved in issue 34)."""
    broken = []
    for page in PAGES:
        text = (ROOT / page).read_text(encoding="utf-8")
        for target in re.findall(r"\]\(([^)\s]+)\)", text):
            if re.match(r"^[a-z]+://|^#|^mailto:", target):
                continue
            path = ((ROOT / page).parent / target.split("#")[0]).resolve()
            if not path.exists():
                broken.append(f"{page}: {target}")
    assert not broken, broken
