"""Time from a `python -m src.run` command to its answer, for the common mistakes and for an accepted
`stage=config`: each command run as its own process (what a user waits for: the interpreter, the imports,
the check, Hydra), in rounds with a rotating order (`src.bench.timing.time_rounds`), median and quartiles
per command. With `--before DIR` the same commands also run in another checkout (e.g. a worktree of an
older commit) in the same rounds, so both columns are measured under the same load."""

from __future__ import annotations

import itertools
import re
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import torch

from src.bench.timing import Spread, device_name, time_rounds
from src.errors import ConfigError, DataError
from src.provenance import git_commit

REPO = Path(__file__).resolve().parents[2]

#: id -> (what the mistake is, the command line's arguments after `python -m src.run`).
CASES: dict[str, tuple[str, list[str]]] = {
    "model_typo": ("misspelt model", ["model=kpcnn"]),
    "key_typo": ("misspelt key", ["task.train.epoch=3"]),
    "key_no_group": ("key without its group", ["train.epochs=3"]),
    "sweep_no_m": ("sweep without -m", ["model=kpcn,dpcn"]),
    "plus_existing": ("+ on a key that exists", ["+seed=3"]),
    "group_null": ("config group set to null", ["model=null"]),
    "other_task_model": ("model of another task", ["profile=smoke", "model=nerf", "stage=config"]),
    "bad_value": ("value out of range", ["profile=smoke", "task.train.batch_size=-4", "stage=config"]),
    "accepted": ("accepted (stage=config)", ["profile=smoke", "stage=config"]),
}

#: A log line's leading `[2026-11-29 00:24:10,841]`.
TIME_STAMP = re.compile(r"^\[\d{4}-\d\d-\d\d [\d:,]+\]")

#: Seconds after which one command counts as hung (the bench stops with a one-line error).
COMMAND_TIMEOUT_S = 300


@dataclass
class Outcome:
    """The last run of one command in one checkout: its exit status, the number of lines it printed
    (stdout and stderr) and the first of them without its log time stamp (a refused command's error)."""

    status: int | None = None
    lines: int = 0
    first_line: str = ""
    seconds: list[float] = field(default_factory=list)


def command_runner(checkout: Path, args: list[str], out_dir: Path, outcome: Outcome):
    """A function that runs `python -m src.run *args` in `checkout` (its `src` is the one imported) with
    its output folder under `out_dir`, and records its exit status and what it printed in `outcome`."""
    runs = itertools.count()

    def run() -> None:
        folder = out_dir / str(next(runs))
        try:
            done = subprocess.run(
                [sys.executable, "-m", "src.run", *args, f"hydra.run.dir={folder}"],
                cwd=checkout,
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                text=True,
                timeout=COMMAND_TIMEOUT_S,
                check=False,
            )
        except subprocess.TimeoutExpired:
            raise DataError(
                f"python -m src.run {' '.join(args)}: no answer within {COMMAND_TIMEOUT_S} s in {checkout}"
            ) from None
        lines = [line for line in done.stdout.splitlines() if line.strip()]
        outcome.status, outcome.lines = done.returncode, len(lines)
        outcome.first_line = TIME_STAMP.sub("", lines[0]) if lines else ""

    return run


def selected_cases(text: str) -> list[str]:
    """The case ids of `--cases` (comma-separated; 'all' = every one), checked against CASES."""
    if text == "all":
        return list(CASES)
    ids = [part.strip() for part in text.split(",") if part.strip()]
    unknown = [i for i in ids if i not in CASES]
    if unknown or not ids:
        raise ConfigError(
            f"--cases: unknown {', '.join(unknown) or '(none given)'}; expected some of {', '.join(CASES)}"
        )
    return ids


def checkouts(before: str | None) -> dict[str, Path]:
    """The checkouts timed: 'after' (this one) and, with --before, that folder (it must hold src/run.py)."""
    timed = {"after": REPO}
    if before is not None:
        folder = Path(before).resolve()
        if not (folder / "src" / "run.py").is_file():
            raise ConfigError(f"--before {before}: no src/run.py there; expected a checkout of this project")
        timed = {"before": folder, **timed}
    return timed


def short_commit(checkout: Path) -> str:
    """The checkout's commit, 12 digits, and `+dirty` when its tracked files differ from it."""
    commit = git_commit(checkout)
    return commit[:12] + ("+dirty" if commit.endswith("+dirty") else "")


def cell(spread: Spread) -> str:
    return f"{spread.median:.2f} [{spread.q1:.2f}, {spread.q3:.2f}]"


def startup_table(cases: list[str], outcomes: dict[tuple[str, str], Outcome], sides: list[str]) -> str:
    """A markdown table: per case, per checkout, the median seconds [quartiles], the exit status, the
    number of lines printed and the first of them."""
    head = (
        "| command | "
        + " | ".join(f"{s}: s (median [q1, q3]) | {s}: exit, lines: first" for s in sides)
        + " |"
    )
    rows = [head, "|" + "---|" * (1 + 2 * len(sides))]
    for case in cases:
        what, args = CASES[case]
        cells = []
        for side in sides:
            o = outcomes[side, case]
            line = o.first_line if len(o.first_line) <= 110 else o.first_line[:107] + "..."
            cells += [cell(Spread.of(o.seconds)), f"{o.status}, {o.lines}: `{line}`"]
        rows.append(f"| {what}: `{' '.join(args)}` | " + " | ".join(cells) + " |")
    return "\n".join(rows)


def run_startup(args) -> str:
    cases, timed = selected_cases(args.cases), checkouts(args.before)
    outcomes = {(side, case): Outcome() for side in timed for case in cases}
    cpu = torch.device("cpu")
    with tempfile.TemporaryDirectory(prefix="nrbench-startup-") as tmp:
        fns = {
            f"{side}/{case}": command_runner(
                path, CASES[case][1], Path(tmp) / side / case, outcomes[side, case]
            )
            for side, path in timed.items()
            for case in cases
        }
        rounds = time_rounds(fns, cpu, rounds=args.rounds, warmup=args.warmup)
    for name, seconds in rounds.seconds.items():
        side, case = name.split("/")
        outcomes[side, case].seconds = seconds
    header = (
        f"# Command to answer: `python -m src.run ...` as a process, wall clock from its start to its exit "
        f"(interpreter, imports, checks, Hydra); {args.rounds} rounds in a rotating order after "
        f"{args.warmup} untimed; {device_name(cpu)}; checkouts: "
        + ", ".join(f"{side} = commit {short_commit(path)}" for side, path in timed.items())
    )
    return header + "\n\n" + startup_table(cases, outcomes, list(timed))
