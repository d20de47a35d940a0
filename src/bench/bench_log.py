"""`--log`: a benchmark's result as one MLflow run, for reports and ledgers that compare benchmark runs.

The run goes to experiment `nrbench-bench` of the store `MLFLOW_TRACKING_URI` names (else, as for
`python -m src.run`, `sqlite:///<cwd>/mlflow.db` with artifacts under `<cwd>/mlartifacts`), through
`src.tracking.mlflow_tracking.standalone_run` (git provenance tags). What it holds, for a reader that
selects runs by param `bench` and tag `nrbench.profile`:
- params: `bench` (the subcommand) and the benchmark's settings (width, height, rounds, warmup, device,
  tile, ...);
- tags: `nrbench.profile`, `nrbench.device`, `nrbench.git_commit`, `nrbench.git_dirty`, ...;
- metrics: `seconds_<model>`, each timed row's median seconds per frame over the rounds;
- artifacts: `bench/rounds.csv`, one row per timed row per round (columns round, model, seconds; round
  from 0, rows in the order they ran), and `bench/report.txt`, the printed report.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Mapping, Sequence
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from src.bench.denoise_timing import Row
from src.bench.timing import Rounds
from src.io.atomic import atomic_write_csv
from src.tracking.mlflow_tracking import standalone_run

EXPERIMENT = "nrbench-bench"
ROUNDS_CSV = "bench/rounds.csv"
ROUNDS_COLUMNS = ("round", "model", "seconds")


def tracking_config(root: Path | None = None) -> DictConfig:
    """The store and experiment: `MLFLOW_TRACKING_URI`, else conf/config.yaml's default under `root`
    (the current directory)."""
    root = (root or Path.cwd()).resolve()
    uri = os.environ.get("MLFLOW_TRACKING_URI") or f"sqlite:///{root}/mlflow.db"
    return OmegaConf.create(
        {"uri": uri, "experiment": EXPERIMENT, "artifact_root": str(root / "mlartifacts")}
    )


def write_rounds_csv(path: Path, rounds: Rounds) -> Path:
    """`rounds` as the `bench/rounds.csv` table (columns round, model, seconds), written atomically."""
    return atomic_write_csv(path, rounds.csv_rows(), ROUNDS_COLUMNS)


def log_bench_run(
    bench: str,
    params: Mapping[str, object],
    tags: Mapping[str, str],
    rows: Sequence[Row],
    rounds: Rounds,
    report: str,
) -> str:
    """Log one benchmark run (module docstring); returns its run id."""
    with standalone_run(tracking_config(), run_name=f"bench-{bench}", tags=tags) as tracker:
        tracker.log_params({"bench": bench, **params})
        timed = [r for r in rows if r.key in rounds.seconds]
        tracker.log_metrics({f"seconds_{r.key}": r.seconds for r in timed})
        with tempfile.TemporaryDirectory(prefix="nrbench-bench-") as tmp:
            path = write_rounds_csv(Path(tmp) / Path(ROUNDS_CSV).name, rounds)
            tracker.log_artifact(path, str(Path(ROUNDS_CSV).parent))
        tracker.log_text(report, "bench/report.txt")
        return tracker.run_id
