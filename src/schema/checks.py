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
    """The schema model of the mapping at `loc` (None when loc leaves the schema models); list indices and
    union members' tags in loc are steps inside one field, not keys."""
    for part in loc:
        if isinstance(part, int) or _is_tag(part):
            continue
        field = model.model_fields.get(str(part)) if model is not None else None
        if field is None:
            return None
        model = next(iter(_models_in(field.annotation)), None)
    return model


def _models_in(annotation: Any) -> list[type[BaseModel]]:
    """The schema models an annotation holds: itself, a union's members, a list's or a mapping's items."""
    found = []
    for plain in _plain_types(annotation):
        if isinstance(plain, type) and issubclass(plain, BaseModel):
            found.append(plain)
        elif typing.get_origin(plain) in (list, dict):
            found += _models_in(typing.get_args(plain)[-1])
    return found


def _is_tag(part: Any) -> bool:
    """Whether a loc part is one of pydantic's labels rather than a key: a union member (`float`,
    `constrained-int`, `literal['a']`, `list[float]`, `function-after[...]`, a model's class name) or a
    mapping's `[key]` marker."""
    text = str(part)
    return text in _TYPE_TAGS or text.startswith(_TAG_PREFIXES) or text in _model_names()


#: pydantic-core's labels of union members and validators in an error's loc (keys never look like these).
_TYPE_TAGS = ("float", "int", "str", "bool", "none", "[key]")
_TAG_PREFIXES = (
    "constrained-",
    "function-",
    "lax-or-strict[",
    "is-instance[",
    "literal[",
    "nullable[",
    "list[",
    "dict[",
    "tuple[",
)


def _model_names() -> set[str]:
    """The class names of every schema model: pydantic tags a union member that is a model by its name."""
    names, todo = set(), [BaseModel]
    while todo:
        cls = todo.pop()
        for sub in cls.__subclasses__():
            names.add(sub.__name__)
            todo.append(sub)
    return names


def _field(model: type[BaseModel], loc: Sequence[Any]):
    """The schema field at `loc` (None when loc leaves the schema models)."""
    parent = _model_at(model, loc[:-1]) if loc else None
    return parent.model_fields.get(str(loc[-1])) if parent is not None else None


def _noun(model: type[BaseModel], loc: Sequence[Any]) -> str:
    """ "integer" for an int field, else "number" (the field's type, not the value's: lr=0 is a number); an
    item of a list or mapping field (`spp[0]`, `table.k`) by the field's item type."""
    loc = [part for part in loc if not _is_tag(part)]
    end = next((end for end in range(len(loc), 0, -1) if _field(model, loc[:end]) is not None), 0)
    kinds = _plain_types(_field(model, loc[:end]).annotation) if end else set()
    if end and end < len(loc):
        kinds = {t for k in kinds for t in _plain_types((typing.get_args(k) or (None,))[-1])}
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
        "int_parsing": "expected an integer",
        "float_parsing": "expected a number",
        "bool_parsing": "expected true or false",
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
        elif not _is_tag(part):  # union members and validators name themselves in loc: not keys
            parts.append(str(part))
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
        raise ConfigError(_first_violation(err.errors(), model, prefix)) from None


def _first_violation(errors: Sequence[ErrorDetails], model: type[BaseModel], prefix: str) -> str:
    """The line of the first key in error. A union reports one error per member: our own validator's
    (the member whose shape the value has) wins, else the members' expectations are joined with "or"."""
    key = _key(prefix, errors[0]["loc"])
    at_key = [e for e in errors if _key(prefix, e["loc"]) == key]
    own = [e for e in at_key if e["type"] in (OWN_ERROR, EXPECTED)]
    if own or len(at_key) == 1:
        return error_line((own or at_key)[0], model, prefix)
    wanted = dict.fromkeys(_expectation(e, model).removeprefix("expected ") for e in at_key)
    return f"{key}={_show(at_key[0].get('input'))}: expected {' or '.join(wanted)}"
