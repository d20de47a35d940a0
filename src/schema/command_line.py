"""The command line's overrides checked before Hydra starts a job: a misspelt config-group option or an
unknown key is one line with the closest names, exit status 2, and no output folder (Hydra creates a
job's folder only after its config composed).

Hydra's own answer to the same mistakes is 10-20 lines: the option list and the config search path for
an option, and for a key a suggestion to add it with `+`, which is the wrong fix when the key is only
misspelt or given without its group (`train.epochs` for `task.train.epochs`). Here the check composes the
config with Hydra's Compose API (the same files and defaults as the job; `difflib` ranks the names) and
only explains a failure; a command that composes goes on to Hydra unchanged.

Only single jobs are composed: a multirun's sweep values (`seed=0,1,2`) are checked option by option for
the config groups, the rest is left to Hydra. Three more mistakes Hydra answers with a traceback or with
advice that hides the fix: a sweep without `-m` (`model=kpcn,dpcn`), a config group set to `null`
(`model=null`, a traceback), and `+key=...` for a key the config already has (`+seed=3`).
"""

from __future__ import annotations

import difflib
from collections.abc import Iterable, Sequence
from pathlib import Path

from src.errors import ConfigError

CONF_DIR = Path(__file__).resolve().parents[2] / "conf"
CONFIG_NAME = "config"
#: Command-line flags after which nothing is run (help, shell completion): no check.
NO_JOB_FLAGS = ("--help", "-h", "--hydra-help", "--info", "-i", "--shell-completion", "-sc")
#: Flags that take a value (the next argument is not an override).
FLAGS_WITH_VALUE = ("--cfg", "-c", "--package", "-p")
#: Flags that point Hydra at other config files: the check, which composes conf/, stands aside.
OTHER_CONFIG_FLAGS = ("--config-path", "-cp", "--config-name", "-cn", "--config-dir", "-cd")


def closest(word: str, names: Iterable[str], n: int = 3) -> list[str]:
    """The names nearest `word` by `difflib`'s ratio (at least 0.6), best first."""
    return difflib.get_close_matches(word, list(names), n=n, cutoff=0.6)


def split_argv(argv: Sequence[str]) -> tuple[list[str], bool, bool]:
    """(the overrides, multirun, whether this check applies) of a `python -m src.run` command line: not
    when nothing runs (help, shell completion) or another config folder or name is given (the check
    composes the project's conf/)."""
    overrides, multirun, skip = [], False, False
    for arg in argv:
        if skip:
            skip = False
        elif arg in ("-m", "--multirun"):
            multirun = True
        elif arg in NO_JOB_FLAGS or arg.startswith("--shell-completion") or arg in OTHER_CONFIG_FLAGS:
            return [], multirun, False
        elif arg in FLAGS_WITH_VALUE:
            skip = True
        elif not arg.startswith("-"):
            overrides.append(arg)
    return overrides, multirun, True


def option_error(group: str, value: str, options: Sequence[str]) -> ConfigError:
    """`model=kpcnn: no such model; did you mean kpcn? (options: ...)`."""
    near = closest(value, options)
    hint = f"did you mean {' or '.join(near)}? " if near else ""
    return ConfigError(f"{group}={value}: no such {group}; {hint}(options: {', '.join(options)})")


def check_sweeps_and_nulls(parsed, options, multirun: bool) -> None:
    """A sweep (`model=kpcn,dpcn`, `seed=range(3)`) on a command line without `-m`, and a config group set
    to `null`: each a ConfigError naming the override and the fix."""
    for override in parsed:
        if override.is_sweep_override() and not multirun:
            key, _, value = override.input_line.partition("=")
            raise ConfigError(
                f"{override.input_line}: a sweep runs one job per value only as a multirun; add -m "
                f"(or, for one value with a comma in it, quote it: {key}='{value}')"
            )
        known = options(override.key_or_group)
        single = not override.is_delete() and not override.is_sweep_override()
        if known and single and override.value() is None:
            raise ConfigError(
                f"{override.input_line}: a config group takes one of its options: {', '.join(known)}"
            )


def check_options(parsed, options) -> None:
    """Each override of a config group (`model=...`, `+sweep=...`, a sweep's `model=a,b`, `hydra/launcher=`)
    names an option of that group (`options(group)`: Hydra's list, user folders on `hydra.searchpath`
    included; empty for a key that is no group); a ConfigError names the first that does not."""
    for override in parsed:
        known = options(override.key_or_group)
        if not known or override.is_delete():
            continue
        values = override.sweep_string_iterator() if override.is_sweep_override() else [override.value()]
        for value in values:
            if value is not None and str(value) not in known:
                raise option_error(override.key_or_group, str(value), known)


def leaf_keys(cfg, prefix: str = "") -> list[str]:
    """Every dotted key of a composed config (nodes and leaves; interpolations are not resolved)."""
    from omegaconf import DictConfig

    keys = []
    for key in cfg:
        dotted = f"{prefix}{key}"
        keys.append(dotted)
        node = cfg._get_node(key)
        if isinstance(node, DictConfig) and not node._is_missing() and not node._is_none():
            keys += leaf_keys(node, f"{dotted}.")
    return keys


def key_error(key: str, keys: Sequence[str]) -> ConfigError:
    """`task.train.epoch: no such config key; did you mean task.train.epochs?`: a key given without its
    group (`train.epochs`) is found by its ending; else the deepest part of it that exists is named with
    the nearest of its keys, or with all of them."""
    with_group = [k for k in keys if k.endswith(f".{key}")]
    if with_group:
        return ConfigError(f"{key}: no such config key; did you mean {' or '.join(with_group)}?")
    parts = key.split(".")
    depth = max((i for i in range(len(parts)) if ".".join(parts[:i]) in keys), default=0)
    parent, missing = ".".join(parts[:depth]), parts[depth]
    children = sorted(k.rpartition(".")[2] for k in keys if k.rpartition(".")[0] == parent)
    near = closest(missing, children)
    where = f"{parent}." if parent else ""
    if near:
        hint = f"did you mean {' or '.join(where + n for n in near)}?"
    elif children:
        hint = f"keys under {parent or 'the root'}: {', '.join(children)}"
    else:
        hint = f"{parent} has no keys"
    return ConfigError(f"{key}: no such config key; {hint}")


def check_keys(parsed, options, searchpath: Sequence[str]) -> None:
    """Compose the config with the group choices of the command line (and its `hydra.searchpath`) and
    check that every other changed key exists in it, and that a `+key` (which adds one) does not (`~key`
    and `++key` are left to Hydra and the schema). A composition this check cannot explain is left to
    Hydra's own error."""
    from hydra import compose

    choices = [o.input_line for o in parsed if options(o.key_or_group)]
    try:
        base = compose(CONFIG_NAME, overrides=[*choices, *searchpath])
    except Exception:  # noqa: BLE001 - Hydra's own error follows when the job starts
        return
    keys = leaf_keys(base)
    for override in parsed:
        key = override.key_or_group
        if options(key) or key.split(".")[0].split("/")[0] == "hydra" or "/" in key:
            continue  # a group choice (checked above) or Hydra's own settings
        if override.is_delete() or override.is_force_add():
            continue
        if override.is_add():
            if has_key(base, key):  # Hydra's answer: "add a second +", which hides that the key exists
                raise ConfigError(
                    f"{override.input_line}: {key} is already in the config; set it without the +: "
                    f"{override.input_line[1:]}"
                )
            continue
        if not has_key(base, key):
            raise key_error(key, keys)


def has_key(cfg, key: str) -> bool:
    """Whether the dotted `key` is in `cfg`, walking its nodes without resolving any value (a value may
    interpolate `${hydra:...}`, which only a running job can resolve); a key inside a list is left to
    Hydra."""
    from omegaconf import DictConfig, ListConfig

    node = cfg
    for part in key.split("."):
        if isinstance(node, ListConfig):
            return True
        if not isinstance(node, DictConfig) or part not in node:
            return False
        node = node._get_node(part)
    return True


def check_command_line(argv: Sequence[str]) -> None:
    """Raise a one-line ConfigError for the first mistake of `argv`: a sweep without -m, a group set to
    null, a misspelt group option, an unknown key or a `+` on a key that exists."""
    from functools import cache

    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.object_type import ObjectType
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    overrides, multirun, applies = split_argv(argv)
    if not applies:
        return
    try:
        parsed = OverridesParser.create().parse_overrides(overrides)
    except OverrideParseException as err:
        raise ConfigError(f"command line: {' '.join(str(err).split())}") from None
    searchpath = [o.input_line for o in parsed if o.key_or_group == "hydra.searchpath"]
    with initialize_config_dir(config_dir=str(CONF_DIR), version_base="1.3"):
        loader = GlobalHydra.instance().config_loader()

        @cache
        def options(group: str) -> list[str]:
            return loader.get_group_options(group, ObjectType.CONFIG, CONFIG_NAME, searchpath)

        check_sweeps_and_nulls(parsed, options, multirun)
        check_options(parsed, options)
        if not multirun and not any(o.is_sweep_override() for o in parsed):
            check_keys(parsed, options, searchpath)
