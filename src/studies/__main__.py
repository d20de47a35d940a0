"""`python -m src.studies`: the ledger's studies at a profile, as jobs: which are done, the time left, and
one command that launches the rest.

    python -m src.studies --profile cpu --dry-run                # every job the ledger needs, done or not
    python -m src.studies --profile paper --study denoisers --dry-run
    python -m src.studies --profile paper hydra/launcher=slurm hydra.launcher.partition=gpu   # launch

Every study's jobs are listed with their state in the tracking store (`MLFLOW_TRACKING_URI`): done (a
FINISHED run of the same configuration digest) or to run, with an estimate from the durations of the
study's done jobs. Without `--dry-run`, each study with jobs to run gets, through the same launcher, first
one job per distinct dataset running its data stages (render, preprocess), then its sweep with
`skip_finished=true`, in which the done jobs end at once. Trailing arguments are Hydra overrides for every
job (a launcher, its partition, `NRBENCH_DATA_DIR` stays an environment variable). Exit 2 on a bad study
name or override, the sweep's own exit status when one fails (rerun the same command to continue).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from collections.abc import Sequence

from src.errors import NrbenchError
from src.studies.plan import CONF, ROOT, StudyJob, estimate_seconds, ledger_studies, study_jobs
from src.tracking.finished import FinishedRun, finished_runs

#: The sweep callbacks a data-only launch leaves out: it has no runs to parent, report or put in the ledger.
NO_SWEEP_CALLBACKS = ("~hydra.callbacks.mlflow_sweep", "~hydra.callbacks.sweep_report")


def _hours(seconds: float | None) -> str:
    if seconds is None:
        return "unknown"
    if seconds < 60:
        return f"{seconds:.0f} s"
    return f"{seconds / 3600:.1f} h" if seconds >= 3600 else f"{seconds / 60:.1f} min"


def plan_lines(
    study: str, jobs: Sequence[StudyJob], done: dict[str, FinishedRun]
) -> tuple[list[str], float, int]:
    """The dry run's lines for one study; (lines, estimated seconds of the jobs to run, how many of them
    have no estimate)."""
    to_run = [j for j in jobs if j.digest not in done]
    estimates = {j.digest: estimate_seconds(j, done, jobs) for j in to_run}
    known = sum(e for e in estimates.values() if e is not None)
    unknown = sum(e is None for e in estimates.values())
    data = len({j.data for j in to_run if j.data_stages})
    if to_run and unknown == len(to_run):
        left = "time left unknown (none of the study done yet)"
    else:
        left = f"time left {_hours(known)} of jobs" + (f" + {unknown} without an estimate" if unknown else "")
    head = (
        f"study {study}: {len(jobs)} jobs, {len(jobs) - len(to_run)} done, {len(to_run)} to run"
        f" ({data} data job{'s' if data != 1 else ''} first); {left}"
    )
    lines = [head]
    for job in jobs:
        run = done.get(job.digest)
        state = f"done    run {run.run_id[:12]} in {_hours(run.seconds)}" if run else "to run"
        estimate = "" if run else f"  ~{_hours(estimates[job.digest])}"
        lines.append(f"  {state:<40} {' '.join(job.overrides)}{estimate}")
    return lines, known, unknown


def _run(command: list[str]) -> int:
    print("+ " + " ".join(command), flush=True)
    return subprocess.run(command, cwd=ROOT).returncode


def launch(study: str, profile: str, jobs: Sequence[StudyJob], done: dict, overrides: Sequence[str]) -> int:
    """The data jobs (one per distinct dataset among the jobs to run), then the sweep; an exit status."""
    base = [sys.executable, "-m", "src.run", "-m", f"+sweep={study}", f"profile={profile}", *overrides]
    firsts = {}
    for job in jobs:
        if job.digest not in done and job.data_stages:
            firsts.setdefault(job.data, job)
    for job in firsts.values():
        stages = f"task.stages=[{','.join(job.data_stages)}]"
        code = _run([*base, *job.overrides, stages, *NO_SWEEP_CALLBACKS])
        if code != 0:
            return code
    return _run([*base, "skip_finished=true"])


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m src.studies", description=__doc__.split("\n\n")[0])
    parser.add_argument("--profile", default="cpu", help="smoke | cpu | paper (default cpu)")
    parser.add_argument("--study", action="append", help="one study (repeatable); default: the ledger's")
    parser.add_argument(
        "--dry-run", action="store_true", help="list the jobs, done or not, and the time left"
    )
    parser.add_argument("overrides", nargs="*", help="Hydra overrides for every job (launcher, partition...)")
    args = parser.parse_args(argv)
    try:
        studies = args.study or ledger_studies(CONF / "claims.yaml", args.profile)
        plans = []
        for study in studies:
            jobs = study_jobs(study, args.profile, args.overrides)
            done = finished_runs(jobs[0].uri, jobs[0].experiment) if jobs else {}
            plans.append((study, jobs, done))
    except NrbenchError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    total, unknown, left = 0.0, 0, 0
    for study, jobs, done in plans:
        lines, known, missing = plan_lines(study, jobs, done)
        print("\n".join(lines))
        total, unknown, left = (
            total + known,
            unknown + missing,
            left + sum(j.digest not in done for j in jobs),
        )
    if left and unknown == left:
        time_left = "time left unknown (no study has a done job)"
    else:
        time_left = f"time left {_hours(total)} of jobs" + (
            f" + {unknown} without an estimate" if unknown else ""
        )
    print(
        f"{len(plans)} studies at profile {args.profile}: {left} jobs to run, {time_left}"
        + (" (run one after another; divide by the jobs run at once)" if total else "")
    )
    if args.dry_run:
        return 0
    for study, jobs, done in plans:
        if all(j.digest in done for j in jobs):
            continue
        code = launch(study, args.profile, jobs, done, args.overrides)
        if code != 0:
            print(
                f"study {study}: exit {code}; the same command continues from the jobs not done",
                file=sys.stderr,
            )
            return code
    return 0


if __name__ == "__main__":
    sys.exit(main())
