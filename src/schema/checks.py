"""Validation of a composed run config against the schemas (`src/schema/*.py`), once, when a job starts:
before any data is read or file written. A bad value becomes one ConfigError line naming the key, the value
found and what is expected (`task.train.batch_size=-4: expected a positive integer`).

Why pydantic rather than Hydra structured configs: Hydra's checks fire while the config is composed, before
the harness gets control, so their messages and exit status cannot be made the harness's; and pydantic
gives ranges, unions and cross-field checks in plain annotations.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Mapping, Sequence
from typing import Any

from pydantic import BaseModel, ValidationError
from pydantic_core import ErrorDetails

from src.errors import ConfigError

#: Error type of our own validators (`types.own_error`): their message is already the whole line.
OWN_ERROR = "nrbench"
#: Error type of a validator that states what it expected (`types.expected`).
EXPECTED = "nrbench_expected"


def _show(value: Any) -> str:
    """A value as a user would type it on the command line."""
    if isinstance(value, bool):
        return str(value).lower()
    if value is None:
        return "null"
    if isinstance(value, str):
        return repr(value)
    return str(value)


def _model_at(model: type[BaseModel] | None, loc: Sequence[Any]) -> type[BaseModel] | None:
    """The schema model of the mapping at `loc` (None when loc leaves the schema models)."""
    for part in loc:
        field = model.model_fields.get(str(part)) if model is not None else None
        if field is None:
            return None
        candidates = _plain_types(field.annotation)
        model = next((c for c in candidates if isinstance(c, type) and issubclass(c, BaseModel)), None)
    return model


def _field(model: type[BaseModel], loc: Sequence[Any]):
    """The schema field at `loc` (None when loc leaves the schema models)."""
    parent = _model_at(model, loc[:-1]) if loc else None
    return parent.model_fields.get(str(loc[-1])) if parent is not None else None


def _noun(model: type[BaseModel], loc: Sequence[Any]) -> str:
    """ "integer" for an int field, else "number" (the field's type, not the value's: lr=0 is a number)."""
    field = _field(model, loc)
    kinds = _plain_types(field.annotation) if field is not None else set()
    return "integer" if int in kinds and float not in kinds else "number"


def _plain_types(annotation: Any) -> set[Any]:
    """The plain types in an annotation: unions flattened, `Annotated[...]` unwrapped."""
    if typing.get_origin(annotation) is typing.Annotated:
        return _plain_types(typing.get_args(annotation)[0])
    args = typing.get_args(annotation)
    if args and typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return set().union(*(_plain_types(a) for a in args))
    return {annotation}


def _expectation(error: ErrorDetails, model: type[BaseModel]) -> str:
    """What the schema expected, in words, for one pydantic error."""
    kind, ctx = error["type"], error.get("ctx", {})
    if kind == EXPECTED:
        return error["msg"]
    bound = next((ctx[k] for k in ("gt", "ge", "lt", "le") if k in ctx), None)
    if kind == "greater_than" and bound == 0:
        return f"expected a positive {_noun(model, error['loc'])}"
    if kind == "greater_than_equal" and bound == 0:
        return f"expected a non-negative {_noun(model, error['loc'])}"
    words = {
        "greater_than": f"expected a value > {bound}",
        "greater_than_equal": f"expected a value >= {bound}",
        "less_than": f"expected a value < {bound}",
        "less_than_equal": f"expected a value <= {bound}",
        "int_type": "expected an integer",
        "int_from_float": "expected an integer",
        "float_type": "expected a number",
        "bool_type": "expected true or false",
        "string_type": "expected a string",
        "list_type": "expected a list",
        "too_short": (
            "expected a non-empty list"
            if ctx.get("min_length") == 1
            else f"expected at least {ctx.get('min_length')} items"
        ),
        "too_long": f"expected at most {ctx.get('max_length')} items",
        "dict_type": "expected a mapping",
        "model_type": "expected a mapping",
        "literal_error": f"expected one of {ctx.get('expected', '')}",
        "string_too_short": "expected a non-empty string",
        "missing": "missing; expected a value",
        "extra_forbidden": f"unknown key; expected one of {_known_keys(model, error['loc'][:-1])}",
    }
    return words.get(kind, f"expected {error['msg'][0].lower()}{error['msg'][1:]}")


def _known_keys(model: type[BaseModel], loc: Sequence[Any]) -> list[str]:
    """The keys the schema allows at `loc` (for an unknown key's message)."""
    found = _model_at(model, loc)
    return [] if found is None else [field.alias or name for name, field in found.model_fields.items()]


def _key(prefix: str, loc: Sequence[Any]) -> str:
    parts = [prefix] if prefix else []
    for part in loc:
        if isinstance(part, int):
            parts[-1] = f"{parts[-1]}[{part}]"
        elif not str(part).startswith(("function-", "literal[", "lax-or-strict", "is-instance")):
            parts.append(str(part))  # union / validator branches name themselves in loc: not keys
    return ".".join(parts)


def error_line(error: ErrorDetails, model: type[BaseModel], prefix: str) -> str:
    """One line for one pydantic error: `<key>=<value>: expected ...`."""
    if error["type"] == OWN_ERROR:
        return error["msg"]
    key = _key(prefix, error["loc"])
    if error["type"] in ("missing", "extra_forbidden"):
        return f"{key}: {_expectation(error, model)}"
    return f"{key}={_show(error.get('input'))}: {_expectation(error, model)}"


def check(model: type[BaseModel], values: Mapping[str, Any], prefix: str = "") -> BaseModel:
    """`values` validated by `model`; the first violation as a one-line ConfigError."""
    try:
        return model.model_validate(dict(values))
    except ValidationError as err:
        raise ConfigError(error_line(err.errors()[0], model, prefix)) from None
