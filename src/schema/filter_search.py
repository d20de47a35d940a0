"""Schema of `task:` for the filter-search task (conf/task/filter_search.yaml and its profiles)."""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field, model_validator

from src.schema.denoise import DenoiseTaskSchema, Eval
from src.schema.types import (
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    Probability,
    Schema,
    own_error,
)

MutationKind = Literal["insert", "replace", "swap", "delete"]


class SeedSigmas(Schema):
    spatial: PositiveFloat
    color: PositiveFloat
    normal: PositiveFloat
    albedo: PositiveFloat
    depth: PositiveFloat


class Search(Schema):
    split: Literal["val", "test"]
    spp: list[PositiveInt] | None
    max_images: PositiveInt | None
    crop: PositiveInt | None
    radius: int = Field(ge=0)
    normalize: bool
    seed_sigmas: SeedSigmas
    islands: PositiveInt
    population: PositiveInt
    generations: int = Field(ge=0)
    migration_interval: PositiveInt
    migrants: PositiveInt
    tournament_size: PositiveInt
    replication: Probability
    crossover: Probability
    mutation: Probability
    crossover_mutation: Probability
    seed_copies: Probability
    mutation_kinds: dict[MutationKind, NonNegativeFloat]
    max_length: PositiveInt
    vector_pairs: Literal["mixed", "same"]
    crossover_points: Literal["type_first", "thesis"]
    shares_count: Literal["draws", "individuals"]
    max_constants: NonNegativeInt | None
    color_variance: bool
    hall_of_fame: NonNegativeInt
    fitness_cache: bool
    fitness_eps: PositiveFloat
    bias_guard: NonNegativeFloat
    tree_batch: PositiveInt
    seed: int = Field(ge=0)
    resume: str | None
    out_dir: str

    @model_validator(mode="after")
    def _consistent(self) -> Search:
        total = self.replication + self.crossover + self.mutation
        if abs(total - 1.0) > 1e-6:
            raise own_error(f"task.search: replication + crossover + mutation = {total:g}; expected 1")
        if not sum(self.mutation_kinds.values()) > 0:
            raise own_error("task.search.mutation_kinds: the weights sum to 0; expected a positive sum")
        seed_constants = 2 * sum(math.isfinite(v) for v in self.seed_sigmas.model_dump().values())
        if self.max_constants is not None and self.max_constants < seed_constants:
            raise own_error(
                f"task.search.max_constants={self.max_constants}: the seed (the cross-bilateral filter of "
                f"task.search.seed_sigmas) has {seed_constants} constants; expected at least that many"
            )
        if self.migrants >= self.population:
            raise own_error(
                f"task.search.migrants={self.migrants}: expected fewer than task.search.population="
                f"{self.population}"
            )
        return self


class FilterSearchTaskSchema(DenoiseTaskSchema):
    stages: list[Literal["render", "preprocess", "search", "eval", "report"]]
    search: Search
    eval: Eval

    @model_validator(mode="after")
    def _held_out(self) -> FilterSearchTaskSchema:
        if self.search.split == self.eval.split:
            raise own_error(
                f"task.search.split={self.search.split!r} is task.eval.split: the search must not train on "
                "the held-out images; expected different splits"
            )
        return self
