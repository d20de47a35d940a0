"""Did a change keep the numbers? Timing-free comparisons used to check refactors (docs/development.md).

python scripts/compare_metrics.py dump  MLFLOW_DB OUT.csv
    every FINISHED job run's eval metrics (timings left out), one row per (model, scene, seed), sorted,
    17 significant digits: dump before and after a change and compare the files byte for byte;
python scripts/compare_metrics.py dvc   BEFORE.json REPO_DIR
    the metrics files of a `dvc metrics show --json` taken before, against the same files in REPO_DIR
    now (timings left out); prints "identical: N files; differing: M; not yet there: K".
"""

from __future__ import annotations

import json
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

#: Substrings of metric names that measure time or speed: they differ between any two runs.
TIMING = ("ms_per", "rays_per", "seconds", "time")


def numbers(tree: Mapping[str, Any], prefix: str = "") -> dict[str, float]:
    """The numeric leaves of a nested metrics dict, as `a.b.c` keys, timings left out."""
    out: dict[str, float] = {}
    for key, value in tree.items():
        if isinstance(value, Mapping):
            out |= numbers(value, f"{prefix}{key}.")
        elif (
            isinstance(value, int | float)
            and not isinstance(value, bool)
            and not any(t in key for t in TIMING)
        ):
            out[prefix + key] = value
    return out


def differences(before: Mapping[str, Any], after: Mapping[str, Any]) -> list[tuple[str, Any, Any]]:
    """(key, before, after) for every non-timing number of `before` that `after` does not equal."""
    now = numbers(after)
    return [(k, v, now.get(k)) for k, v in numbers(before).items() if now.get(k) != v]


def compare_dvc(before_json: Path, repo: Path) -> str:
    before = json.loads(before_json.read_text())[""]["data"]
    same = differ = missing = 0
    for name, entry in sorted(before.items()):
        path = repo / name
        if not path.exists():
            missing += 1
            continue
        diff = differences(entry["data"], json.loads(path.read_text()))
        if diff:
            differ += 1
            print("DIFF", name, diff[:4])
        else:
            same += 1
    return f"identical: {same} files; differing: {differ}; not yet there: {missing}"


def dump_runs(db: Path, out_csv: Path) -> str:
    import mlflow

    mlflow.set_tracking_uri(f"sqlite:///{db}")
    runs = mlflow.search_runs(search_all_experiments=True, filter_string="attributes.status = 'FINISHED'")
    runs = runs[runs["params.seed"].notna()]  # job runs, not sweep parents
    keys = [k for k in ("params.model.name", "params.task.scene", "params.seed") if k in runs]
    metrics = sorted(
        c for c in runs.columns if c.startswith("metrics.eval_") and not any(t in c for t in TIMING)
    )
    runs[keys + metrics].sort_values(keys).to_csv(out_csv, index=False, float_format="%.17g")
    return f"{len(runs)} runs, {len(metrics)} metrics -> {out_csv}"


if __name__ == "__main__":
    command, *args = sys.argv[1:] or ["help"]
    if command == "dump" and len(args) == 2:
        print(dump_runs(Path(args[0]), Path(args[1])))
    elif command == "dvc" and len(args) == 2:
        print(compare_dvc(Path(args[0]), Path(args[1])))
    else:
        print(__doc__)
        sys.exit(2)
