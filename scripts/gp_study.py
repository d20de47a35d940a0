"""Seed spread and paired comparisons of a filter-search study (`+sweep=gp_expansion|gp_rules|gp_bias_guard|
gp_population`), from its job folders: the numbers docs/studies.md quotes.

    python scripts/gp_study.py SWEEP_DIR [--spp 4]

SWEEP_DIR is the multirun folder (`multirun/sweeps/<name>/<date>_<time>`, or `hydra.sweep.dir`); each job
folder holds `.hydra/overrides.yaml`, `search/history.json`, `search/best_expressions.yaml` and
`eval/per_image.csv`. An arm is a job's overrides without `seed` (one arm per study setting). Prints
Markdown:

- per arm, mean ± sample std over its seeds: the search's min fitness (the thesis's measure, Sec. 4.2),
  the held-out relMSE / noisy (Eq. 3.5, the fitness term) at `--spp` (the searched sample count) per
  held-out scene and over them, and over every sample count; PSNR; energy (mean output / mean reference,
  the truth 1) per scene;
- per job: its seed, min fitness, held-out ratio at `--spp` and best expression;
- each arm against the first (paired by seed and held-out image, `src.report.paired`): the
  geometric-mean ratio of relMSE / noisy, the PSNR and |energy - 1| differences, wins, and the Wilcoxon
  p-value, at `--spp` and over all sample counts; "significant (n = ...)" at p < 0.05, "not significant
  (n = ...)" otherwise.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a file: make `src` importable
    sys.path.insert(0, str(ROOT))

from src.errors import DataError  # noqa: E402
from src.report.paired import paired_difference  # noqa: E402

JOB_FILES = (
    ".hydra/overrides.yaml",
    "search/history.json",
    "search/best_expressions.yaml",
    "eval/per_image.csv",
)


def load_job(folder: Path) -> dict:
    """One job: its arm (overrides without seed and the sweep itself), seed, min fitness, best expression,
    held-out rows."""
    missing = [f for f in JOB_FILES if not (folder / f).is_file()]
    if missing:
        raise DataError(f"{folder}: no {missing[0]} (a finished filter-search job expected)")
    overrides = yaml.safe_load((folder / JOB_FILES[0]).read_text())
    seed = next((o.split("=", 1)[1] for o in overrides if o.startswith("seed=")), "-")
    arm = " ".join(o for o in overrides if o.split("=")[0] not in ("seed", "+sweep", "profile"))
    history = json.loads((folder / JOB_FILES[1]).read_text())
    best = yaml.safe_load((folder / JOB_FILES[2]).read_text())
    return {
        "job": folder.name,
        "arm": arm or "-",
        "seed": seed,
        "min_fitness": min(i["best"] for h in history for i in h["islands"]),
        "expression": best[0]["model"]["expression"],
        "rows": pd.read_csv(folder / JOB_FILES[3]),
    }


def load_jobs(sweep: Path) -> tuple[list[dict], list[str]]:
    """The sweep's finished jobs in job order (folders named 0, 1, ...), and the unfinished ones' names
    (no `eval/per_image.csv` yet: a sweep still running)."""
    if not sweep.is_dir():
        raise DataError(f"{sweep}: not a folder; expected a filter-search multirun folder")
    folders = sorted(
        (d for d in sweep.iterdir() if d.is_dir() and d.name.isdigit()), key=lambda d: int(d.name)
    )
    done = [d for d in folders if (d / JOB_FILES[-1]).is_file()]
    if not done:
        raise DataError(f"{sweep}: no finished job folders (0, 1, ... with {JOB_FILES[-1]})")
    return [load_job(d) for d in done], [d.name for d in folders if d not in done]


def _spread(values, digits: int = 4) -> str:
    """Mean ± sample std (the mean alone for one value), `digits` after the point."""
    v = np.asarray(list(values), dtype=float)
    mean = f"{v.mean():.{digits}f}"
    return f"{mean} ± {v.std(ddof=1):.{digits}f}" if len(v) > 1 else mean


def _scene_base(scene: str) -> str:
    return scene.rsplit("-", 1)[0]


def arm_table(jobs: list[dict], spp: int) -> pd.DataFrame:
    """Per arm (first appearance order): seeds and mean ± std over them (module docstring)."""
    rows = []
    for arm in dict.fromkeys(j["arm"] for j in jobs):
        group = [j for j in jobs if j["arm"] == arm]
        at = [j["rows"][j["rows"]["spp"] == spp] for j in group]
        scenes = sorted({s for t in at for s in t["scene"]})
        row = {"arm": arm, "seeds": len(group), "min fitness": _spread(j["min_fitness"] for j in group)}
        for scene in scenes:
            row[f"relMSE/noisy {_scene_base(scene)}"] = _spread(
                t.loc[t["scene"] == scene, "relmse_ratio"].mean() for t in at
            )
        row[f"relMSE/noisy {spp} spp"] = _spread(t["relmse_ratio"].mean() for t in at)
        row["relMSE/noisy all spp"] = _spread(j["rows"]["relmse_ratio"].mean() for j in group)
        row[f"PSNR {spp} spp"] = _spread((t["psnr"].mean() for t in at), 2)
        for scene in scenes:
            energy = (t.loc[t["scene"] == scene, "energy"].mean() for t in at)
            row[f"energy {_scene_base(scene)}"] = _spread(energy, 3)
        rows.append(row)
    return pd.DataFrame(rows)


def _paired_rows(jobs: list[dict], arm: str, spp: int | None) -> pd.DataFrame:
    frames = []
    for j in jobs:
        if j["arm"] == arm:
            t = j["rows"] if spp is None else j["rows"][j["rows"]["spp"] == spp]
            frames.append(t.assign(seed=j["seed"]))
    return pd.concat(frames).set_index(["seed", "scene", "spp"]).sort_index()


def comparisons(jobs: list[dict], spp: int) -> pd.DataFrame:
    """Each arm against the first, paired by (seed, scene, spp) (module docstring)."""
    arms = list(dict.fromkeys(j["arm"] for j in jobs))
    rows = []
    for arm in arms[1:]:
        for at in (spp, None):
            a, b = _paired_rows(jobs, arm, at), _paired_rows(jobs, arms[0], at)
            common = a.index.intersection(b.index)
            if common.empty:
                continue
            a, b = a.loc[common], b.loc[common]
            ratio = paired_difference(a["relmse_ratio"], b["relmse_ratio"], log=True)
            psnr = paired_difference(a["psnr"], b["psnr"])
            energy = paired_difference((a["energy"] - 1).abs(), (b["energy"] - 1).abs())
            rows.append(
                {
                    "arm vs first": arm,
                    "spp": "all" if at is None else at,
                    "pairs": ratio.n,
                    "relMSE/noisy ratio": f"{ratio.ratio:.3f}",
                    "lower/higher": f"{ratio.b_higher}/{ratio.a_higher}",
                    "p": f"{ratio.p_value:.3g}",
                    "relMSE": ratio.verdict(),
                    "PSNR diff (dB)": f"{psnr.mean_difference:+.2f}",
                    "p PSNR": f"{psnr.p_value:.3g}",
                    "|energy-1| diff": f"{energy.mean_difference:+.4f}",
                    "p energy": f"{energy.p_value:.3g}",
                }
            )
    return pd.DataFrame(rows)


def job_table(jobs: list[dict], spp: int) -> pd.DataFrame:
    return pd.DataFrame(
        {
            "arm": j["arm"],
            "seed": j["seed"],
            "min fitness": f"{j['min_fitness']:.4f}",
            f"relMSE/noisy {spp} spp": f"{j['rows'].loc[j['rows']['spp'] == spp, 'relmse_ratio'].mean():.3f}",
            "expression": j["expression"],
        }
        for j in jobs
    )


def report(sweep: Path, spp: int) -> str:
    jobs, unfinished = load_jobs(sweep)
    parts = [f"# {sweep}", ""]
    if unfinished:
        parts += [f"Unfinished jobs left out: {', '.join(unfinished)}.", ""]
    parts += [arm_table(jobs, spp).to_markdown(index=False), ""]
    paired = comparisons(jobs, spp)
    if not paired.empty:
        parts += [paired.to_markdown(index=False), ""]
    parts += [job_table(jobs, spp).to_markdown(index=False)]
    return "\n".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sweep", type=Path, help="the multirun folder of a filter-search study")
    parser.add_argument("--spp", type=int, default=4, help="the searched sample count (default 4)")
    args = parser.parse_args(argv)
    try:
        print(report(args.sweep, args.spp))
    except (DataError, OSError) as err:
        print(f"gp_study: {err}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
