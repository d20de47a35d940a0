"""Constrained value types the schemas share, and the base every schema model derives from."""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import AfterValidator, BaseModel, ConfigDict, Field
from pydantic_core import PydanticCustomError

from src.errors import ConfigError
from src.schema.checks import EXPECTED, OWN_ERROR

PositiveInt = Annotated[int, Field(gt=0)]
NonNegativeInt = Annotated[int, Field(ge=0)]
PositiveFloat = Annotated[float, Field(gt=0)]
NonNegativeFloat = Annotated[float, Field(ge=0)]
Probability = Annotated[float, Field(ge=0, le=1)]
AtLeastOne = Annotated[float, Field(ge=1)]
Percentile = Annotated[float, Field(gt=0, le=100)]


class Schema(BaseModel):
    """Strict (a string is not a number, 1 is not true) and closed (an unknown key is an error)."""

    model_config = ConfigDict(strict=True, extra="forbid", populate_by_name=True)


class Open(BaseModel):
    """A section whose keys are checked elsewhere (or are free-form): any keys, values as given."""

    model_config = ConfigDict(extra="allow")


class Target(BaseModel):
    """A `_target_` node built with hydra.utils.instantiate: the dotted path, `_partial_`, and the
    target's own keyword arguments (checked by the target when it is built)."""

    model_config = ConfigDict(extra="allow", populate_by_name=True, strict=True)
    target: str = Field(alias="_target_", min_length=1)
    partial: bool = Field(default=False, alias="_partial_")


def expected(text: str) -> PydanticCustomError:
    """An error of a value whose expectation a validator states (`<key>=<value>: <text>`)."""
    return PydanticCustomError(EXPECTED, "{text}", {"text": text})


def _ordered(pair: list[float]) -> list[float]:
    if pair[0] > pair[1]:
        raise expected("expected [lo, hi] with lo <= hi")
    return pair


#: A uniform range [lo, hi] of the procedural scene families.
Range = Annotated[list[float], Field(min_length=2, max_length=2), AfterValidator(_ordered)]
Colour = Annotated[list[Annotated[float, Field(ge=0)]], Field(min_length=3, max_length=3)]


def own_error(message: str) -> PydanticCustomError:
    """An error whose message is already the whole line (from the check a builder would make itself)."""
    return PydanticCustomError(OWN_ERROR, "{message}", {"message": message})


def passes(check, value: Any) -> Any:
    """`value` if `check(value)` accepts it; its ConfigError as an `own_error` otherwise."""
    try:
        check(value)
    except ConfigError as err:
        raise own_error(str(err)) from None
    return value


def known_loss(value: Any) -> Any:
    """A loss setting (`task.train.loss`, `dataset.train.loss`) as the trainer checks it (`get_loss`): a known
    name, or an importable `_target_` mapping."""
    from src.objectives.losses import get_loss

    passes(get_loss, value if isinstance(value, str) else value.model_dump(by_alias=True, exclude_unset=True))
    return value
