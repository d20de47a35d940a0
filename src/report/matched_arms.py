"""Whether two arms' runs are a like-for-like comparison, and whether a run was made at its profile's budget.

A difference between arms is the method's only when everything else is equal: the data (fingerprint),
the code (commit, or commits declared equivalent in `ledger.equivalent_commits`) and every config key
outside the arms' own. `first_confound` names the first key that breaks this. Keys that differ between
arms by design are declared on the claim (`rule.ratio`: b's value over a's, e.g. DPCN's twice-as-many
epochs) and checked at that ratio.

A run tagged with a profile counts at it only at that profile's budget: its command-line overrides
(`nrbench.hydra_job`) must not change a key that a profile file sets (`profile_keys`), nor pick another
profile file, unless the claim compares or selects by that key (a study's swept budget is its arm).
"""

from __future__ import annotations

import shlex
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path

import pandas as pd
from omegaconf import OmegaConf

from src.report.collect import differing_params
from src.report.renamed_keys import renamed_key

#: The config groups whose files say what a profile means (conf/config.yaml's defaults list).
PROFILE_GROUPS = (
    "profile",
    "task_profile",
    "dataset_profile",
    "model_profile",
    "dataset_task_profile",
    "model_task_profile",
    "task_dataset_profile",
)
#: The profile groups whose files belong to one model (named <model>_<profile>.yaml).
MODEL_GROUPS = ("model_profile", "model_task_profile")
#: Params that vary between the replicates and items of one comparison by design.
REPLICATE_PARAMS = ("data_seed", "seed", "task.scene")
HYDRA_JOB_TAG = "tags.nrbench.hydra_job"
#: Keys the harness derives from an arm's keys, and the prefix of the keys they follow: the sequences' input
#: features and channel counts (dataset and model) follow the feature selection at job start (src/kinds/),
#: and the random
#: arm draws its subset with the training seed (conf/selection_arm/random.yaml).
DERIVED_FROM = {
    "dataset.volume_features": "dataset.feature_selection.",
    "dataset.input_channels": "dataset.feature_selection.",
    "model.in_channels": "dataset.feature_selection.",
    "dataset.feature_selection.random_seed": "dataset.feature_selection.",
}


def _leaves(node: object, prefix: str) -> Iterable[str]:
    if isinstance(node, Mapping):
        for key, value in node.items():
            yield from _leaves(value, f"{prefix}.{key}" if prefix else str(key))
    elif prefix:
        yield prefix


def _file_keys(path: Path, group: str) -> set[str]:
    """The dotted keys a config group file sets, under its `# @package` header (default: the group)."""
    text = path.read_text()
    package = next(
        (ln.split("@package", 1)[1].strip() for ln in text.splitlines() if "@package" in ln), group
    )
    prefix = "" if package == "_global_" else package
    return set(_leaves(OmegaConf.to_container(OmegaConf.create(text or "{}")), prefix))


def profile_keys(conf_dir: Path) -> frozenset[str]:
    """Every dotted config key a profile file sets (conf/<group>/*.yaml for `PROFILE_GROUPS`, each under
    its `# @package` header): the budget and sizes a profile decides."""
    keys: set[str] = set()
    for group in PROFILE_GROUPS:
        for path in sorted((conf_dir / group).glob("*.yaml")):
            keys |= _file_keys(path, group)
    return frozenset(keys)


def model_keys(conf_dir: Path) -> dict[str, frozenset[str]]:
    """Per model (conf/model/<name>.yaml), the keys its own profile files set outside `model.`
    (conf/model_profile/<name>_<profile>.yaml, conf/model_task_profile/<name>_<profile>.yaml): the
    model's recipe (NeRF's precrop iterations, DPCN's epochs), which belong to the arm that picks it."""
    names = [p.stem for p in sorted((conf_dir / "model").glob("*.yaml"))]
    profiles = [p.stem for p in sorted((conf_dir / "profile").glob("*.yaml"))]
    owned: dict[str, frozenset[str]] = {}
    for name in names:
        keys: set[str] = set()
        for group in MODEL_GROUPS:
            for profile in profiles:
                path = conf_dir / group / f"{name}_{profile}.yaml"
                if path.is_file():
                    keys |= _file_keys(path, group)
        owned[name] = frozenset(keys)
    return owned


def _override_keys(hydra_job: str) -> list[str]:
    """The config keys a job's overrides set (`+key=v`, `++key=v`, `key=v`; a deletion `~key` too), under
    today's names (`renamed_keys`: a run logged before a key moved overrode its old name)."""
    try:
        words = shlex.split(hydra_job)
    except ValueError:  # an unbalanced quote: the plain words still name the keys
        words = hydra_job.split()
    return [renamed_key(w.split("=", 1)[0].lstrip("+~")) for w in words if "=" in w or w.startswith("~")]


def _covers(key: str, keys: Iterable[str]) -> bool:
    return any(key == k or key.startswith(f"{k}.") or k.startswith(f"{key}.") for k in keys)


def off_profile_key(hydra_job: object, budget: frozenset[str], allowed: Sequence[str]) -> str:
    """The first override of `hydra_job` that moves a run off its profile's budget ("" when none): a key
    a profile file sets, or another profile file, that is not in `allowed` (the claim's arm and
    `where` keys)."""
    if not isinstance(hydra_job, str):
        return ""
    for key in _override_keys(hydra_job):
        if key == "profile" or _covers(key, allowed):  # choosing the profile is what the tag records
            continue
        if key in PROFILE_GROUPS[1:] or _covers(key, budget):
            return key
    return ""


def derived_keys(arm_keys: Iterable[str]) -> list[str]:
    """The keys `DERIVED_FROM` says follow one of `arm_keys` (they belong to the arm too)."""
    return [key for key, prefix in DERIVED_FROM.items() if any(k.startswith(prefix) for k in arm_keys)]


def canonical_value(value: object) -> str:
    """A param value as compared: booleans and numbers by value ("True" = "true", "0.0" = "0"), a missing
    one as "<unset>", the rest as text (MLflow stores every param as a string)."""
    text = "<unset>" if value is None or (isinstance(value, float) and pd.isna(value)) else str(value).strip()
    if text.lower() in ("true", "false"):
        return text.lower()
    try:
        return repr(float(text))
    except ValueError:
        return text


def _ratio_broken(key: str, a: pd.Series, b: pd.Series, ratio: float) -> str | None:
    va, vb = {canonical_value(v) for v in a}, {canonical_value(v) for v in b}
    if not va or not vb:  # an arm without runs (a study under way): the claim reads "no scores for arm"
        return None
    if len(va) > 1 or len(vb) > 1:
        return f"{key} varies within an arm ({sorted(va)} / {sorted(vb)})"
    try:
        x, y = float(va.pop()), float(vb.pop())
    except ValueError:
        return f"{key} is not a number in both arms"
    if x == 0 or abs(y / x - ratio) > 1e-9 * ratio:
        return f"{key}: b / a = {y:g} / {x:g}, the claim declares {ratio:g}"
    return None


def first_confound(
    a_runs: pd.DataFrame,
    b_runs: pd.DataFrame,
    arm_keys: Sequence[str],
    ratio: Mapping[str, float],
    equivalent_commits: Sequence[Sequence[str]] = (),
) -> str | None:
    """The first thing that differs between the compared runs besides the arms' own keys, the seeds and
    scenes, and the declared `ratio` keys; None when the runs are matched."""
    runs = pd.concat([a_runs, b_runs])
    commit = _commit_group(runs, equivalent_commits)
    if commit:
        return commit
    fingerprint = "tags.nrbench.data_fingerprint"
    if fingerprint in runs:
        within = [c for c in ("params.data_seed", "params.task.scene") if c in runs]
        groups = runs.groupby(within, dropna=False) if within else [("", runs)]
        for _, part in groups:
            values = sorted({canonical_value(v) for v in part[fingerprint]})
            if len(values) > 1:
                return f"data fingerprint differs ({', '.join(values)})"
    for key, value in ratio.items():  # declared by the claim: checked whether or not the arms differ
        column = f"params.{key}"
        if column not in runs:
            return f"{key} (rule.ratio {value:g}) is not among the runs' params"
        broken = _ratio_broken(key, a_runs[column], b_runs[column], value)
        if broken:
            return broken
    # The arms' own keys, the replicate keys, paths and outputs aside (collect.differing_params).
    for key in differing_params(runs, [*arm_keys, *REPLICATE_PARAMS, *ratio]):
        values = sorted({canonical_value(v) for v in runs[f"params.{key}"]})
        if len(values) > 1:  # "0" and "0.0" differ as text, not as values
            return f"{key} differs ({', '.join(values[:4])})"
    return None


def _commit_group(runs: pd.DataFrame, equivalent: Sequence[Sequence[str]]) -> str | None:
    column = "tags.nrbench.git_commit"
    if column not in runs:
        return None
    commits = sorted({str(c) for c in runs[column].dropna()})

    def group(commit: str) -> str:
        for members in equivalent:
            if any(commit.startswith(str(m)) or str(m).startswith(commit) for m in members):
                return str(members[0])
        return commit

    if len({group(c) for c in commits}) > 1:
        return f"code commit differs ({', '.join(c[:10] for c in commits)})"
    return None
