"""Typed readers of a `model:` config mapping, shared by the denoiser and radiance-field builders.

Each returns the value of `model.<key>` or raises a one-line `ConfigError` naming the key, what was found
and what was expected. `bool` is rejected where a number is expected: it is an `int` subclass, and
`width: true` is a typo, not 1.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError, require


def as_dict(model_cfg: Mapping[str, Any]) -> dict[str, Any]:
    """A plain resolved dict of a model config (DictConfig or mapping)."""
    if isinstance(model_cfg, DictConfig):
        return OmegaConf.to_container(model_cfg, resolve=True)  # type: ignore[return-value]
    if not isinstance(model_cfg, Mapping):
        raise ConfigError(f"model: expected a mapping, got {type(model_cfg).__name__}")
    return dict(model_cfg)


def value(cfg: Mapping[str, Any], key: str) -> Any:
    return require(cfg, key, "model", f"model {cfg.get('name')!r}")


def integer(cfg: Mapping[str, Any], key: str, minimum: int = 1, odd: bool = False) -> int:
    found = value(cfg, key)
    if isinstance(found, bool) or not isinstance(found, int) or found < minimum or (odd and found % 2 == 0):
        kind = "an odd integer" if odd else "an integer"
        raise ConfigError(f"model.{key}: expected {kind} >= {minimum}, got {found!r}")
    return found


def optional_integer(cfg: Mapping[str, Any], key: str) -> int | None:
    """An integer >= 0, or None when the key is null or absent."""
    return None if cfg.get(key) is None else integer(cfg, key, minimum=0)


def number(cfg: Mapping[str, Any], key: str, minimum: float | None = None) -> float:
    found = value(cfg, key)
    too_small = minimum is not None and isinstance(found, int | float) and found < minimum
    if isinstance(found, bool) or not isinstance(found, int | float) or too_small:
        bound = "" if minimum is None else f" >= {minimum}"
        raise ConfigError(f"model.{key}: expected a number{bound}, got {found!r}")
    return float(found)


def boolean(cfg: Mapping[str, Any], key: str) -> bool:
    found = value(cfg, key)
    if not isinstance(found, bool):
        raise ConfigError(f"model.{key}: expected true or false, got {found!r}")
    return found


def choice(cfg: Mapping[str, Any], key: str, allowed: Sequence[str]) -> str:
    found = value(cfg, key)
    if found not in allowed:
        raise ConfigError(f"model.{key}: unknown {found!r}; expected one of {list(allowed)}")
    return found
