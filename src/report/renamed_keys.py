"""Config keys that moved, so that runs logged before a move are read under today's names.

MLflow keeps each run's params under the key it had when the run was logged. When a key moves (the data
kinds' own options moved from `task:` to `dataset:` at issue 44), the study store holds both spellings;
the reports and the ledger read every run through `renamed_params`, and a run's command-line overrides
(its `nrbench.hydra_job` tag) through `renamed_key`, so a claim or an axis names one key and finds the runs
of both. A key is renamed by prefix: `task.feature_selection.size` -> `dataset.feature_selection.size`.
"""

from __future__ import annotations

import pandas as pd

#: old prefix -> new prefix, each a whole dotted key or a dotted key's leading part.
RENAMED: dict[str, str] = {
    "task.volume_features": "dataset.volume_features",
    "task.feature_selection": "dataset.feature_selection",
    "task.preprocess.volume_transform": "dataset.preprocess.volume_transform",
    "task.preprocess.sequence_frames": "dataset.preprocess.sequence_frames",
    "task.preprocess.patches_per_sequence": "dataset.preprocess.patches_per_sequence",
    "task.train.volumetric": "dataset.train",
    "task.preprocess.eps_albedo": "dataset.preprocess.eps_albedo",
    "task.preprocess.specular_variance": "dataset.preprocess.specular_variance",
    "task.preprocess.patches_per_image": "dataset.preprocess.patches_per_image",
    "task.preprocess.patches_per_split": "dataset.preprocess.patches_per_split",
}


def renamed_key(key: str) -> str:
    """`key` under today's name (unchanged when it never moved); a `+`/`++`/`~` override prefix is kept."""
    sign = key[: len(key) - len(key.lstrip("+~"))]
    bare = key[len(sign) :]
    for old, new in RENAMED.items():
        if bare == old or bare.startswith(old + "."):
            return sign + new + bare[len(old) :]
    return key


def renamed_params(runs: pd.DataFrame) -> pd.DataFrame:
    """`runs` (as `mlflow.search_runs` gives them) with every `params.<old key>` column read as
    `params.<new key>`: where both exist (runs logged before and after a move), each run keeps the value
    it logged."""
    moved = {
        c: "params." + renamed_key(c.removeprefix("params.")) for c in runs.columns if c.startswith("params.")
    }
    moved = {old: new for old, new in moved.items() if old != new}
    if not moved:
        return runs
    out = runs.drop(columns=list(moved))
    for old, new in moved.items():
        out[new] = runs[old] if new not in out else out[new].where(out[new].notna(), runs[old])
    return out
