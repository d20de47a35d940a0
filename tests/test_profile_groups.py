"""The profile groups (conf/config.yaml's `optional ..._profile` entries): each file writes one group, its
name selects it, and the resolved configs stay what tests/data/resolved_config_digests.json records."""

import importlib.util
import itertools
import json
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
spec = importlib.util.spec_from_file_location("resolved_configs", ROOT / "scripts" / "resolved_configs.py")
resolved_configs = importlib.util.module_from_spec(spec)
spec.loader.exec_module(resolved_configs)

CONF = ROOT / "conf"
TEST_CONF = ROOT / "tests" / "conf"  # the toy models' own profile files (hydra.searchpath)
#: The group a profile group's files write (their `# @package`), from the group's name: `<keyed by>_
#: <writes>_profile`, or `<writes>_profile` when keyed by the choice of the group it writes.
WRITES = {
    "task_profile": "task",
    "dataset_profile": "dataset",
    "model_profile": "model",
    "dataset_task_profile": "task",
    "model_task_profile": "task",
    "task_dataset_profile": "dataset",
}


def package(path):
    """A config's `# @package` header (its first line), or None."""
    first = path.read_text().splitlines()[0]
    return first.removeprefix("# @package ") if first.startswith("# @package ") else None


def group_keys(group):
    """Every top-level key a config of conf/<group>/ (or a toy one) has: a global one's `<group>:` block
    (task=nerf and task=filter_search are global), the packages its defaults fill
    (`/encoding@position_encoding`) and the keys of a file its defaults merge into it
    (`sequences/options@_here_`, the sequence kinds' options) included."""
    keys = set()
    for path in [*(CONF / group).glob("*.yaml"), *(TEST_CONF / group).glob("*.yaml")]:
        data = yaml.safe_load(path.read_text()) or {}
        for entry in data.get("defaults", []):
            name = next(iter(entry)) if isinstance(entry, dict) else entry
            if name.endswith("@_here_"):
                keys |= set(
                    yaml.safe_load((path.parent / f"{name.removesuffix('@_here_')}.yaml").read_text())
                )
                continue
            keys |= {name.split("@", 1)[1]} if "@" in name and not name.startswith("override") else set()
        keys |= set(data[group] if package(path) == "_global_" else data)
    return keys - {"defaults", group}  # filter_search's `/task/denoise@task` fills the group itself


def profile_files():
    """(group, path) of every profile-group file, the toy models' included."""
    for group in WRITES:
        for root in (CONF, TEST_CONF):
            for path in sorted((root / group).glob("*.yaml")):
                yield group, path


def test_the_profile_groups_are_the_ones_config_yaml_loads():
    assert set(resolved_configs.profile_groups()) == set(WRITES)
    on_disk = {p.name for p in CONF.iterdir() if p.is_dir() and p.name.endswith("_profile")}
    assert on_disk == set(WRITES)


@pytest.mark.parametrize("group,path", list(profile_files()), ids=lambda x: getattr(x, "name", x))
def test_a_profile_file_writes_only_its_own_group(group, path):
    """`# @package <group>` (a `_global_` file could write any group, as every one did before) and only
    keys that group's configs have (a leftover `task:` or `dataset:` block would write task.task.*)."""
    assert package(path) == WRITES[group], f"{path}: # @package {package(path)}; expected {WRITES[group]}"
    data = yaml.safe_load(path.read_text()) or {}
    unknown = set(data) - {"defaults"} - group_keys(WRITES[group])
    assert not unknown, f"{path}: keys {sorted(unknown)} are not {WRITES[group]} keys"


def test_the_profile_files_set_only_the_two_root_keys():
    for path in (CONF / "profile").glob("*.yaml"):
        assert package(path) == "_global_"
        assert set(yaml.safe_load(path.read_text())) == {"profile_name", "profile_tasks"}, path


def choices(key):
    stems = {p.stem for root in (CONF, TEST_CONF) for p in (root / key).glob("*.yaml")}
    return stems if key != "task" else stems & set(resolved_configs.TASK_DATASETS)


@pytest.mark.parametrize("group", list(WRITES))
def test_every_profile_file_is_named_for_choices_that_exist(group):
    """A group is optional, so a file whose name no choice produces (a typo, a renamed model) would be
    skipped without a word."""
    pattern = resolved_configs.profile_groups()[group]
    keys = [part.strip("${}") for part in pattern.split("_${")]
    names = {"_".join(parts) for parts in itertools.product(*(sorted(choices(k)) for k in keys))}
    for _, path in (entry for entry in profile_files() if entry[0] == group):
        assert path.stem in names, f"{path}: no {pattern} names it"


def expected_digests():
    return json.loads(resolved_configs.DIGESTS.read_text())


def check_digests(names):
    """Each combination's resolved config has the digest recorded; on a difference, the keys that moved
    are found with `scripts/resolved_configs.py dump` before and after and `compare`."""
    expected = expected_digests()
    got = {name: resolved_configs.digest(cfg) for name, cfg in resolved_configs.dump(names).items()}
    assert sorted(got) == sorted(names)
    changed = [name for name in names if got[name] != expected[name]]
    assert not changed, (
        f"resolved configs changed: {changed}; if on purpose, compare dumps and "
        "rewrite tests/data/resolved_config_digests.json (scripts/resolved_configs.py digests --write)"
    )


def test_the_recorded_combinations_are_todays():
    assert sorted(name for name, _ in resolved_configs.combinations()) == sorted(expected_digests())


def test_a_few_combinations_load_every_profile_file():
    names = resolved_configs.covering()
    by_name = dict(resolved_configs.combinations())
    loaded = set().union(*(resolved_configs.profile_files(o) for o in by_name.values()))
    assert set().union(*(resolved_configs.profile_files(by_name[n]) for n in names)) == loaded
    assert len(names) < 30


@pytest.mark.parametrize("name", resolved_configs.covering())
def test_a_combination_that_loads_a_profile_file_resolves_as_recorded(name):
    """The fast check (about 0.2 s each); the slow test below composes all combinations."""
    check_digests([name])


@pytest.mark.slow
def test_every_combination_resolves_as_recorded():
    check_digests([name for name, _ in resolved_configs.combinations()])


def test_the_comparison_names_each_changed_key_and_its_combinations():
    before = {"a": {"dataset": {"width": 24, "views": {"train": 4}}}, "b": {"dataset": {"width": 24}}}
    after = {"a": {"dataset": {"views": {"train": 5}}}, "b": {"dataset": {"width": 24}}, "c": {}}
    assert resolved_configs.differences(before, after) == {
        "<combination> only after": ["c"],
        "dataset.views.train: 4 -> 5": ["a"],
        "dataset.width: 24 -> '<absent>'": ["a"],
    }
    assert resolved_configs.differences(before, before) == {}
    # A null that disappears is a difference too (scene_params: null is not the key's absence).
    gone = resolved_configs.differences({"a": {"k": None, "j": 1}}, {"a": {"j": 1}})
    assert gone == {"k: None -> '<absent>'": ["a"]}
