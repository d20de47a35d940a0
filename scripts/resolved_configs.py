"""Did a config refactor keep the numbers? Every run configuration that matters, composed and resolved.

python scripts/resolved_configs.py dump OUT.json
    composes every combination of task x dataset x profile x model (`combinations()`) as `python -m
    src.run` would, resolves it with fixed stand-in paths, and writes {combination: resolved config}
    (a combination that fails to compose or resolve is stored as {"error": message}); run it before and
    after a change to conf/;
python scripts/resolved_configs.py compare BEFORE.json AFTER.json [--renamed]
    every difference between two dumps, one line per changed key with the combinations it changed in;
    prints "identical: N combinations" and exits 0 when there is none, else 1. --renamed reads BEFORE's
    keys under today's names first (src/report/renamed_keys.py: keys that moved, e.g. the sequences'
    options from task: to dataset:), so only values that changed are left;

The combinations: each task with each dataset it reads (denoise and filter_search: procedural, volumetric;
nerf: nerf_procedural, blender with a stand-in root), each profile that has sizes for the task
(`profile_tasks` of conf/profile/<profile>.yaml) and each model of the task's family in conf/model/
(denoisers for denoise and filter_search, `family: nerf` for nerf). tests/test_resolved_configs.py keeps
the digests of today's configs (tests/data/resolved_config_digests.json), so a change that alters one
fails until the digests are rewritten on purpose (`digests --write`).

python scripts/resolved_configs.py digests [--write]
    the sha256 of each combination's resolved config; --write stores them as the test's expected digests.
"""

from __future__ import annotations

import functools
import hashlib
import json
import sys
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
CONF = ROOT / "conf"
DIGESTS = ROOT / "tests" / "data" / "resolved_config_digests.json"

#: The datasets each task reads.
TASK_DATASETS = {
    "denoise": ["procedural", "volumetric"],
    "filter_search": ["procedural", "volumetric"],
    "nerf": ["nerf_procedural", "blender"],
}
#: Extra overrides a dataset needs to compose (a user's Blender scenes have no default folder).
DATASET_OVERRIDES = {"blender": ["dataset.root=/x"]}
#: Stand-ins for what a Hydra run or the environment would set (as tests/conftest.py::smoke_config).
STAND_INS = [
    "paths.root=/nrbench",
    "paths.data=/nrbench/data",
    "paths.run_dir=/nrbench/run",
    "tracking.uri=sqlite:////nrbench/mlflow.db",
    "tracking.artifact_root=/nrbench/mlartifacts",
    "report.out_dir=/nrbench/reports",
]


@functools.cache
def _yaml(path: Path) -> dict[str, Any]:
    import yaml

    return yaml.safe_load(path.read_text()) or {}


def _models(task: str) -> list[str]:
    """conf/model's models of the task's family: NeRF's for nerf, every other for the denoising tasks."""
    names = []
    for path in sorted((CONF / "model").glob("*.yaml")):
        family = _yaml(path).get("family")
        if family is None:  # a model that inherits (kpcn from dpcn) has no family of its own: a denoiser
            family = "denoise"
        if (family == "nerf") == (task == "nerf"):
            names.append(path.stem)
    return names


def combinations() -> Iterator[tuple[str, list[str]]]:
    """(name, overrides) of every combination, in a fixed order."""
    profiles = {p.stem: _yaml(p)["profile_tasks"] for p in sorted((CONF / "profile").glob("*.yaml"))}
    for task, datasets in TASK_DATASETS.items():
        for dataset in datasets:
            for profile, tasks in profiles.items():
                if task not in tasks:
                    continue
                for model in _models(task):
                    choice = [f"task={task}", f"dataset={dataset}", f"profile={profile}", f"model={model}"]
                    yield " ".join(choice), choice + DATASET_OVERRIDES.get(dataset, [])


def profile_groups() -> dict[str, str]:
    """{group: name pattern} of conf/config.yaml's optional profile groups, e.g. {"task_profile":
    "${task}_${profile}"}: the files a combination loads are the patterns filled with its choices."""
    out = {}
    for entry in _yaml(CONF / "config.yaml")["defaults"]:
        if isinstance(entry, dict):
            ((key, value),) = entry.items()
            if key.startswith("optional ") and "${" in str(value):
                out[key.removeprefix("optional ")] = value
    return out


def profile_files(overrides: list[str]) -> set[str]:
    """The profile-group files (`<group>/<name>.yaml`) a combination's choices load."""
    choices = dict(o.split("=", 1) for o in overrides if "." not in o.split("=", 1)[0])
    names = {f"{group}/{pattern}" for group, pattern in profile_groups().items()}
    for key, value in choices.items():
        names = {name.replace("${" + key + "}", value) for name in names}
    return {f"{name}.yaml" for name in names if (CONF / f"{name}.yaml").is_file()}


def covering() -> list[str]:
    """A few combinations that together load every profile-group file some combination loads (greedy
    set cover, in `combinations()` order): the fast test's, the full set being slow."""
    loads = {name: profile_files(overrides) for name, overrides in combinations()}
    left = set().union(*loads.values())
    chosen = []
    while left:
        best = max(loads, key=lambda name: len(loads[name] & left))
        chosen.append(best)
        left -= loads[best]
    return chosen


def resolved(overrides: list[str]) -> dict[str, Any]:
    """The root config these overrides compose, resolved (with the stand-in paths), or {"error": ...};
    inside `initialize_config_dir(CONF)`."""
    from hydra import compose
    from omegaconf import OmegaConf

    try:
        cfg = compose(config_name="config", overrides=[*overrides, *STAND_INS])
        return OmegaConf.to_container(cfg, resolve=True)  # type: ignore[return-value]
    except Exception as err:  # noqa: BLE001  (a failure is part of what must stay the same)
        return {"error": f"{type(err).__name__}: {err}"}


def dump(names: list[str] | None = None) -> dict[str, dict[str, Any]]:
    """{combination: resolved config} of every combination (or of these)."""
    from hydra import initialize_config_dir

    import src  # noqa: F401  (registers the nrbench.* resolvers)

    chosen = [(n, o) for n, o in combinations() if names is None or n in names]
    with initialize_config_dir(config_dir=str(CONF), version_base="1.3"):
        return {name: resolved(overrides) for name, overrides in chosen}


def digest(config: Mapping[str, Any]) -> str:
    return hashlib.sha256(json.dumps(config, sort_keys=True).encode()).hexdigest()


def flat(tree: Any, prefix: str = "") -> dict[str, Any]:
    """The leaves of a nested config as `a.b.c` keys (lists are leaves)."""
    if not isinstance(tree, Mapping) or not tree:
        return {prefix.rstrip("."): tree}
    out: dict[str, Any] = {}
    for key, value in tree.items():
        out |= flat(value, f"{prefix}{key}.")
    return out


def differences(
    before: Mapping[str, Any], after: Mapping[str, Any], renamed: bool = False
) -> dict[str, list[str]]:
    """{"key: before -> after": [combinations]} of every leaf that differs, a combination missing from
    one side as the key `<combination>`. `renamed`: BEFORE's keys are read under today's names first
    (`src/report/renamed_keys.py`), so a moved key with its value kept is no difference."""
    out: dict[str, list[str]] = {}
    for name in sorted(set(before) | set(after)):
        if name not in before or name not in after:
            side = "before" if name in before else "after"
            out.setdefault(f"<combination> only {side}", []).append(name)
            continue
        old, new = flat(before[name]), flat(after[name])
        if renamed:
            from src.report.renamed_keys import renamed_key

            old = {renamed_key(k): v for k, v in old.items()}
        for key in sorted(set(old) | set(new)):
            if old.get(key, "<absent>") != new.get(key, "<absent>") or (key in old) != (key in new):
                change = f"{key}: {old.get(key, '<absent>')!r} -> {new.get(key, '<absent>')!r}"
                out.setdefault(change, []).append(name)
    return out


def main(argv: list[str]) -> int:
    sys.path.insert(0, str(ROOT))
    if argv[:1] == ["dump"] and len(argv) == 2:
        Path(argv[1]).write_text(json.dumps(dump(), indent=1, sort_keys=True))
        return 0
    if argv[:1] == ["compare"] and len(argv) in (3, 4) and argv[3:] in ([], ["--renamed"]):
        before, after = (json.loads(Path(p).read_text()) for p in argv[1:3])
        diffs = differences(before, after, renamed=argv[3:] == ["--renamed"])
        for change, names in diffs.items():
            print(f"{change}  [{len(names)}: {', '.join(names)}]")
        if not diffs:
            print(f"identical: {len(before)} combinations")
        return 1 if diffs else 0
    if argv[:1] == ["digests"] and argv[1:] in ([], ["--write"]):
        digests = {name: digest(config) for name, config in dump().items()}
        if argv[1:] == ["--write"]:
            DIGESTS.parent.mkdir(parents=True, exist_ok=True)
            DIGESTS.write_text(json.dumps(digests, indent=1, sort_keys=True) + "\n")
        else:
            print(json.dumps(digests, indent=1, sort_keys=True))
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
