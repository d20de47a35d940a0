"""Build a method (denoiser, filter, radiance field) from its `model:` config group.

`model._target_` names the class or factory (any importable dotted path, in this repository or the
user's own package); every other key of the group is one of its keyword arguments, so the constructor
signature is the contract between a YAML file and its code (the lightning-hydra-template convention;
the method is called directly, nested `_target_` groups go through `hydra.utils.instantiate`, except for
an argument annotated as a `Mapping`: that method builds the group itself, with its own checks, e.g. the
radiance fields' encodings). A few
keys are read by the harness itself and not passed on (`HARNESS_KEYS`). Before anything is built, the
keys are checked against the signature, so that a typo, a missing value or a wrong type is a one-line
`ConfigError` naming `model.<key>` rather than a `TypeError` deep inside Hydra: Hydra's own errors span
several lines and name no config key.
"""

from __future__ import annotations

import inspect
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any

import hydra.utils
from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError, one_line

#: Keys of a `model:` group that the harness reads (run names, whether to train, the task family); they are
#: not arguments of the method.
HARNESS_KEYS = ("name", "learned", "family")
TARGET_KEY = "_target_"


def model_dict(model_cfg: Mapping[str, Any]) -> dict[str, Any]:
    """A plain resolved dict of a model config (DictConfig or mapping)."""
    if isinstance(model_cfg, DictConfig):
        return OmegaConf.to_container(model_cfg, resolve=True)  # type: ignore[return-value]
    if not isinstance(model_cfg, Mapping):
        raise ConfigError(f"model: expected a mapping, got {type(model_cfg).__name__}")
    return dict(model_cfg)


def resolve_target(node: Mapping[str, Any], section: str = "model") -> Callable[..., Any]:
    """The class or factory `<section>._target_` names (a method's `model:` group, a `task:` group...)."""
    target = node.get(TARGET_KEY)
    if not isinstance(target, str) or not target:
        raise ConfigError(
            f"{section}.{TARGET_KEY}: expected the dotted path of a class or factory "
            f"(e.g. src.models.denoise.models.conv_stack_denoiser), got {target!r}"
        )
    try:
        found = hydra.utils.get_object(target)
    except Exception as err:  # ImportError, AttributeError, or whatever the module raises on import
        raise ConfigError(f"{section}.{TARGET_KEY}: cannot import {target!r} ({one_line(err)})") from None
    if not callable(found):
        raise ConfigError(
            f"{section}.{TARGET_KEY}: {target!r} is a {type(found).__name__}, not a class or function"
        )
    return found


def _conforms(value: Any, hint: Any) -> bool:
    """Whether a config value fits a plain type hint (int, float, bool, str, Literal, X | None, unions).

    A bool is not an int here (`width: true` is a typo, not 1), an int is a float, and hints this does not
    understand (tensors, mappings...) accept anything: the constructor checks those itself.
    """
    origin = typing.get_origin(hint)
    if origin is typing.Literal:
        return value in typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_conforms(value, arm) for arm in typing.get_args(hint))
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, int | float) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    return True


def _describe(hint: Any) -> str:
    text = str(hint).replace("typing.", "").replace("NoneType", "None")
    return text.removeprefix("<class '").removesuffix("'>")


def arguments_of(target: Callable[..., Any]) -> tuple[dict[str, Any], set[str], bool]:
    """(argument -> type hint, required arguments, whether any other keyword is accepted) of `target`.

    `**kwargs: Unpack[SomeTypedDict]` (PEP 692) counts as the TypedDict's keys, so that options several
    methods share can be declared and typed once (see `src.models.nerf.builders.FieldArgs`).
    """
    try:
        hints = typing.get_type_hints(target.__init__ if inspect.isclass(target) else target)
    except Exception:  # annotations that do not resolve: leave the checks to the constructor
        hints = {}
    accepted: dict[str, Any] = {}
    required: set[str] = set()
    takes_any = False
    for key, param in inspect.signature(target).parameters.items():
        if param.kind is param.VAR_POSITIONAL:
            continue
        if param.kind is param.VAR_KEYWORD:
            hint = hints.get(key)
            if typing.get_origin(hint) is typing.Unpack:
                shared = typing.get_args(hint)[0]
                accepted |= typing.get_type_hints(shared)
                # `__required_keys__` misses NotRequired under postponed annotations (Python < 3.14)
                marked = typing.get_type_hints(shared, include_extras=True)
                optional = {k for k, h in marked.items() if typing.get_origin(h) is typing.NotRequired}
                required |= set(shared.__required_keys__) - optional
            else:
                takes_any = True
            continue
        accepted[key] = hints.get(key, typing.Any)
        if param.default is param.empty:
            required.add(key)
    return accepted, required, takes_any


def check_arguments(
    target: Callable[..., Any],
    arguments: tuple[dict[str, Any], set[str], bool],
    kwargs: Mapping[str, Any],
    provided: set[str],
    section: str = "model",
) -> None:
    """Every key is an argument of `target` (its `arguments_of`), of the annotated type; every required
    argument is given (by the config, or by the harness in `provided`). Errors name `<section>.<key>`
    (a nested group, e.g. `model.position_encoding`, passes its own section)."""
    accepted, required, takes_any = arguments
    name = getattr(target, "__qualname__", repr(target))
    for key in kwargs:
        if key not in accepted and not takes_any:
            raise ConfigError(
                f"{section}.{key}: not an argument of {name}; expected one of {sorted(accepted)}"
            )
    for key in sorted(required - set(kwargs) - provided):
        raise ConfigError(f"{section}.{key}: missing; {name} needs it")
    for key, value in kwargs.items():
        if key in accepted and not _conforms(value, accepted[key]):
            raise ConfigError(f"{section}.{key}: expected {_describe(accepted[key])}, got {value!r}")


def at_least(key: str, value: float, minimum: float = 1, odd: bool = False) -> float:
    """`value` of `model.<key>` if it is >= `minimum` (and odd, when asked), else a one-line ConfigError
    naming the key: the range checks a method's builder adds to the type checks of `build_method`."""
    if value < minimum or (odd and value % 2 == 0):
        kind = "an odd number" if odd else "a number"
        raise ConfigError(f"model.{key}: expected {kind} >= {minimum}, got {value!r}")
    return value


def build_method(model_cfg: Mapping[str, Any], section: str = "model", **context: Any) -> Any:
    """The method `model._target_` names, called with the group's other keys as keyword arguments.

    `section` is the config key errors name (`model`, or e.g. `task.eval.baseline` for a method the task
    evaluates beside the run's). `context` holds what the harness knows at run time (e.g. `whitening`,
    the training split's input statistics); each item is passed only to a method whose signature asks for
    it by name.
    """
    cfg = model_dict(model_cfg)
    target = resolve_target(cfg, section)
    kwargs = {k: v for k, v in cfg.items() if k not in HARNESS_KEYS and k != TARGET_KEY}
    arguments = arguments_of(target)
    accepted, _, takes_any = arguments
    wanted = {k: v for k, v in context.items() if k in accepted or takes_any}
    check_arguments(target, arguments, kwargs, set(wanted), section)
    # Nested `_target_` groups (e.g. a user's sub-network) are built by Hydra, unless the method takes the
    # group itself (a Mapping); the method is called directly, so that run-time objects (statistics,
    # tensors) reach it as they are, not as OmegaConf nodes.
    kwargs = {k: v if _takes_mapping(accepted.get(k)) else _build_nested(v) for k, v in kwargs.items()}
    try:
        return target(**kwargs, **wanted)
    except ConfigError:
        raise
    except (TypeError, ValueError) as err:  # a value the constructor rejects (e.g. an even conv kernel)
        raise ConfigError(f"{section} ({cfg.get('name', cfg[TARGET_KEY])}): {one_line(err)}") from None


def _takes_mapping(hint: Any) -> bool:
    return (typing.get_origin(hint) or hint) in (Mapping, dict)


def _build_nested(value: Any) -> Any:
    if isinstance(value, dict) and TARGET_KEY in value:
        return hydra.utils.instantiate(value, _convert_="all")
    return value
