"""The genetic-programming search for filter weight expressions (Davletaliyev 2016, Sec. 3.2.3-3.2.6), on
DEAP's operators.

    population  `islands` islands of `population` individuals each (the island model, Sec. 3.2.5), seeded
                only from the bilateral filter: `seed_copies` (10%) copies of it, the rest one mutation
                of it each (Sec. 3.2.5, "Initial Population")
    generation  per island, a whole new population of the same size (Sec. 3.2.6): each draw is a
                replication (a tournament winner, unchanged), a crossover (two winners, both children
                kept, each then mutated with probability 0.85) or a mutation (one winner); tournaments of 8
                (`tools.selTournament`; lowest fitness wins); every child longer than `max_length` (75
                nodes) is replaced by its parent (`gp.staticLimit`). The 10/45/45 % shares count
                (`shares_count`) individuals (the default, the thesis's "45% of nodes are generated from
                crossovers": the crossover draw is weighted by 1/2, so 10/45/45 % of the new individuals)
                or draws (the ablation, nrbench's first rule: a crossover adds two children, so the
                individuals split 6.9/62/31 %)
    migration   every `migration_interval` (5) generations a copy of each island's best replaces the worst
                of the next island, i -> (i + 1) mod n (`tools.migRing`, Sec. 3.2.5)
    fitness     mean over the training images of relMSE(filtered) / relMSE(noisy), relMSE of Eq. 3.5
                (its m/2 factor cancels in the ratio); an undefined expression (NaN/Inf weights or a zero
                weight sum on any image) gets the worst fitness, `WORST` = the largest float (Sec. 3.2.3)
    result      the best individual of each island (Sec. 3.2.6, "Top expressions from every island"): the
                first of its hall of fame (DEAP's `tools.HallOfFame`, the best `hall_of_fame` distinct
                expressions the island ever held, updated after every generation; the thesis keeps the top
                10 of each island, Sec. 3.3.4, the default), so a best that a later generation lost is
                still reported; with `hall_of_fame: 0` the best of its last generation
    cache       fitness by expression text (`fitness_cache`, on by default): an expression evaluated once
                is never evaluated again (replicas, unchanged crossover children, mutations that give a
                tree back); a value does not depend on what it was batched with, so the cache changes no
                result, only skips work. `evaluations` in the history still counts the distinct new
                expressions of a generation, cached or not; `GPSearch.cache_hits` counts the skipped ones

The variation operators (the codebook, the four mutations, the typed crossover and the length limit) are
`src.gp.variation`'s, the fitness `src.gp.fitness`'s; this module is the island model that drives them and
its checkpoints.

Determinism: DEAP and `src.gp.grammar` draw from Python's global `random`; `GPSearch` seeds it with
`params.seed` at the start and saves `random.getstate()` after every generation, restoring it before the
next, so a run is reproducible and a run resumed from its checkpoint (`save_state` / `load_state`, written
atomically after each generation) gives the same generations as the uninterrupted run.
"""

from __future__ import annotations

import copy
import json
import random
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from deap import base, gp, tools

from src.errors import DataError
from src.gp.fitness import WORST
from src.gp.grammar import ALL_VARIABLES, EXTRA_VARIABLES, PSET, VECTORS, Vector
from src.gp.text import parse, to_infix
from src.gp.variation import CROSSOVER_RULES, MUTATION_KINDS, VECTOR_PAIRS, Variation, count_constants
from src.io.atomic import atomic_write_json

STATE_FORMAT = "nrbench-gp-search-v1"
#: What the expansion shares count (`SearchParams.shares_count`, module docstring).
SHARES_COUNTS = ("draws", "individuals")
#: Parameters that change no result: a checkpoint of a search with other values of them resumes.
RESULT_FREE = ("generations", "fitness_cache")


class FitnessMin(base.Fitness):
    """One objective, minimised (the normalised relMSE)."""

    weights = (-1.0,)


class Individual(gp.PrimitiveTree):
    """An expression tree with its fitness."""

    def __init__(self, content: Iterable) -> None:
        super().__init__(content)
        self.fitness = FitnessMin()


@dataclass(frozen=True)
class SearchParams:
    """Every number of the search; defaults are the thesis's (Davletaliyev 2016, Sec. 3.2.5-3.2.6)."""

    islands: int = 4
    population: int = 100  # per island (400 in all)
    generations: int = 200
    migration_interval: int = 5
    migrants: int = 1
    tournament_size: int = 8
    replication: float = 0.10
    crossover: float = 0.45
    mutation: float = 0.45
    crossover_mutation: float = 0.85  # probability that a crossover child is also mutated
    seed_copies: float = 0.10  # fraction of each island that is the unmodified seed
    mutation_kinds: Mapping[str, float] = field(
        default_factory=lambda: {"insert": 0.3, "replace": 0.3, "swap": 0.3, "delete": 0.1}
    )
    max_length: int = 75
    seed: int = 0
    # The search rules (src.gp.variation and this module's docstrings): the thesis's by default; the
    # other choices are the rules of nrbench's first searches, kept as ablations.
    vector_pairs: str = "same"  # ablation: "mixed"
    crossover_points: str = "thesis"  # ablation: "type_first"
    shares_count: str = "individuals"  # ablation: "draws"
    max_constants: int | None = None  # a cap per expression; the thesis restricts the constant set instead
    hall_of_fame: int = 10  # per island (Sec. 3.3.4); 0: none (the result is the last generation's best)
    fitness_cache: bool = True  # changes no result (not part of a checkpoint's parameters)
    color_variance: bool = True  # colorVariance among the terminals (Sec. 3.2.1.2, Scalar Variables)

    def __post_init__(self) -> None:
        total = self.replication + self.crossover + self.mutation
        if abs(total - 1.0) > 1e-6:
            raise ValueError(f"replication + crossover + mutation = {total:g}; expected 1")
        unknown = set(self.mutation_kinds) - set(MUTATION_KINDS)
        if unknown:
            raise ValueError(f"unknown mutation kind(s) {sorted(unknown)}; expected some of {MUTATION_KINDS}")
        if not sum(self.mutation_kinds.values()) > 0:
            raise ValueError("mutation_kinds: the weights must not all be 0")
        if self.vector_pairs not in VECTOR_PAIRS:
            raise ValueError(f"vector_pairs={self.vector_pairs!r}; expected one of {list(VECTOR_PAIRS)}")
        if self.crossover_points not in CROSSOVER_RULES:
            raise ValueError(
                f"crossover_points={self.crossover_points!r}; expected one of {list(CROSSOVER_RULES)}"
            )
        if self.shares_count not in SHARES_COUNTS:
            raise ValueError(f"shares_count={self.shares_count!r}; expected one of {list(SHARES_COUNTS)}")
        if self.hall_of_fame < 0:
            raise ValueError(f"hall_of_fame={self.hall_of_fame}; expected >= 0")

    def draw_weights(self) -> tuple[float, float, float]:
        """Per-draw probabilities of replication, crossover and mutation: the shares themselves when they
        count draws; when they count individuals, the crossover's halved (it adds two) and all three
        renormalised, so the expected split of the new individuals is the shares."""
        r, c, m = self.replication, self.crossover, self.mutation
        if self.shares_count == "individuals":
            c = c / 2
        total = r + c + m
        return r / total, c / total, m / total


# -- grammar restricted to the data ---------------------------------------------------------------------


def search_pset(available: Iterable[str], color_variance: bool = False) -> gp.PrimitiveSetTyped:
    """The grammar (`PSET`) with only the vector terminals and variables in `available` (plus `pixel`,
    always computable): the operators draw terminals from it, so no individual reads a feature the data
    lack. The variables beyond Fig. 3.2 (`colorVariance`) only with `color_variance`. Constants and
    operators are all kept."""
    keep = set(available) | {"pixel"}
    if not color_variance:
        keep -= set(EXTRA_VARIABLES)
    pset = copy.deepcopy(PSET)
    drop = [n for n in (*VECTORS, *ALL_VARIABLES) if n not in keep]
    for type_ in (Vector, float):
        pset.terminals[type_] = [t for t in pset.terminals[type_] if t.name not in drop]
    pset.terms_count -= len(drop)
    if not pset.terminals[Vector]:
        raise ValueError("search grammar: no vector terminal available")
    return pset


# -- the search ------------------------------------------------------------------------------------------


@dataclass
class SearchState:
    """Where a search is: its islands (evaluated), the generation they are, the RNG state to go on with,
    and the per-generation statistics so far."""

    islands: list[list[Individual]]
    generation: int
    random_state: tuple
    history: list[dict[str, Any]]
    halls: list[tools.HallOfFame] | None = None  # per island, with `hall_of_fame` > 0


def island_stats(island: Sequence[Individual]) -> dict[str, Any]:
    """Best and mean fitness (mean over the defined expressions), count of undefined ones, best text."""
    values = [ind.fitness.values[0] for ind in island]
    valid = [v for v in values if v < WORST]
    best = min(island, key=lambda ind: ind.fitness.values[0])
    return {
        "best": min(values),
        "mean": sum(valid) / len(valid) if valid else WORST,
        "invalid": len(values) - len(valid),
        "best_expression": to_infix(best),
    }


class GPSearch:
    """The search (module docstring): `start()` builds and evaluates generation 0, `step(state)` makes
    the next generation, `run()` does it all, checkpointing after each generation."""

    def __init__(
        self,
        fitness: Callable[[Sequence[gp.PrimitiveTree]], list[float]],
        seed_expression: str,
        params: SearchParams,
        pset: gp.PrimitiveSetTyped,
        book: Mapping[type, Sequence[list]],
    ) -> None:
        self.fitness, self.params, self.pset = fitness, params, pset
        self.seed = Individual(parse(seed_expression, pset))
        if len(self.seed) > params.max_length:
            raise ValueError(f"seed has {len(self.seed)} nodes, over max_length={params.max_length}")
        if params.max_constants is not None and count_constants(self.seed) > params.max_constants:
            raise ValueError(
                f"seed has {count_constants(self.seed)} constants, over max_constants={params.max_constants}"
            )
        self.variation = Variation(
            params.mutation_kinds,
            params.max_length,
            pset,
            book,
            crossover_points=params.crossover_points,
            vector_pairs=params.vector_pairs,
            max_constants=params.max_constants,
        )
        self.clone = copy.deepcopy
        self.cache: dict[str, float] = {}
        self.cache_hits = 0

    # -- pieces ------------------------------------------------------------------------------------------
    def seeded_island(self) -> list[Individual]:
        """`seed_copies` of the island the seed itself, the rest one mutation of it each (Sec. 3.2.5)."""
        n = self.params.population
        copies = max(1, round(self.params.seed_copies * n))
        island = [self.clone(self.seed) for _ in range(copies)]
        while len(island) < n:
            (child,) = self.variation.mutate(self.clone(self.seed))
            island.append(child)
        return island

    def evaluate(self, individuals: Sequence[Individual]) -> None:
        """Give every individual without a fitness one; equal trees are evaluated once."""
        todo: dict[str, list[Individual]] = {}
        for ind in individuals:
            if not ind.fitness.valid:
                todo.setdefault(str(ind), []).append(ind)
        if self.params.fitness_cache:
            for text in [t for t in todo if t in self.cache]:
                for ind in todo.pop(text):
                    ind.fitness.values = (self.cache[text],)
                self.cache_hits += 1
        if not todo:
            return
        groups = list(todo.values())
        values = self.fitness([group[0] for group in groups])
        for (text, group), value in zip(todo.items(), values, strict=True):
            for ind in group:
                ind.fitness.values = (value,)
            if self.params.fitness_cache:
                self.cache[text] = value

    def remember(self, state: SearchState) -> None:
        """Put the fitness of every individual of `state` (islands and halls of fame) in the cache: a
        resumed search skips what its checkpoint knows."""
        if self.params.fitness_cache:
            for ind in [i for island in state.islands for i in island] + [
                i for h in state.halls or [] for i in h
            ]:
                self.cache.setdefault(str(ind), ind.fitness.values[0])

    def update_halls(self, state: SearchState) -> None:
        """Each island's hall of fame takes its island's new individuals (with `hall_of_fame` > 0)."""
        if state.halls is not None:
            for hall, island in zip(state.halls, state.islands, strict=True):
                hall.update(island)

    def select(self, island: Sequence[Individual]) -> Individual:
        return self.clone(tools.selTournament(island, 1, tournsize=self.params.tournament_size)[0])

    def offspring(self, island: Sequence[Individual]) -> list[Individual]:
        """A new island of the same size (Sec. 3.2.6): replication, crossover (children mutated with
        `crossover_mutation`) or mutation, per new individual."""
        out = []
        replication, crossover, _ = self.params.draw_weights()
        while len(out) < len(island):
            r = random.random()
            if r < replication:
                out.append(self.select(island))
            elif r < replication + crossover:
                children = self.variation.mate(self.select(island), self.select(island))
                for child in children:
                    if random.random() < self.params.crossover_mutation:
                        (child,) = self.variation.mutate(child)
                    del child.fitness.values
                    out.append(child)
            else:
                (child,) = self.variation.mutate(self.select(island))
                del child.fitness.values
                out.append(child)
        return out[: len(island)]

    def migrate(self, islands: list[list[Individual]]) -> None:
        """A copy of the best `migrants` of island i replaces the worst of island (i + 1) mod n
        (`tools.migRing`, Sec. 3.2.5)."""
        if len(islands) < 2:
            return

        def best_copies(pop, k):
            return [self.clone(ind) for ind in tools.selBest(pop, k)]

        tools.migRing(islands, self.params.migrants, best_copies, replacement=tools.selWorst)

    def _record(self, state: SearchState, evaluations: int) -> None:
        state.history.append(
            {"generation": state.generation, "evaluations": evaluations}
            | {"islands": [island_stats(island) for island in state.islands]}
        )

    # -- driving -----------------------------------------------------------------------------------------
    def start(self) -> SearchState:
        """Generation 0: the seeded islands, evaluated."""
        random.seed(self.params.seed)
        islands = [self.seeded_island() for _ in range(self.params.islands)]
        self.evaluate([ind for island in islands for ind in island])
        state = SearchState(islands, 0, random.getstate(), [], self._new_halls())
        self.update_halls(state)
        self._record(state, sum(len(i) for i in islands))
        return state

    def _new_halls(self) -> list[tools.HallOfFame] | None:
        if self.params.hall_of_fame == 0:
            return None
        return [tools.HallOfFame(self.params.hall_of_fame) for _ in range(self.params.islands)]

    def step(self, state: SearchState) -> SearchState:
        """The next generation of every island, evaluated, then migration when it is due."""
        random.setstate(state.random_state)
        islands = [self.offspring(island) for island in state.islands]
        fresh = [ind for island in islands for ind in island if not ind.fitness.valid]
        self.evaluate(fresh)
        generation = state.generation + 1
        if generation % self.params.migration_interval == 0:
            self.migrate(islands)
        new = SearchState(islands, generation, random.getstate(), list(state.history), state.halls)
        self.update_halls(new)
        self._record(new, len({str(ind) for ind in fresh}))
        return new

    def run(
        self,
        state: SearchState | None = None,
        checkpoint: str | Path | None = None,
        on_generation: Callable[[SearchState], None] | None = None,
        job: Mapping[str, Any] | Callable[[], Mapping[str, Any]] | None = None,
    ) -> SearchState:
        """All `generations` from `state` (or from the start), saving `checkpoint` after each (with `job`:
        what the caller records of the job that wrote it, see `save_state`; a callable is asked at each
        save, e.g. for the search's clock at that generation)."""
        record = job if callable(job) else (lambda: job)
        if state is not None:
            self.remember(state)
        if state is None:
            state = self.start()
            if checkpoint is not None:
                save_state(checkpoint, state, self.params, record())
            if on_generation is not None:
                on_generation(state)
        while state.generation < self.params.generations:
            state = self.step(state)
            if checkpoint is not None:
                save_state(checkpoint, state, self.params, record())
            if on_generation is not None:
                on_generation(state)
        return state


def top_per_island(state: SearchState) -> list[list[Individual]]:
    """Each island's top expressions (Sec. 3.3.4: "the top 10 expressions from every island"), best first,
    in island order: its hall of fame when the search keeps one (the best it ever held), else the one best
    of its last generation (ties: the first)."""
    if state.halls is not None:
        return [list(hall) for hall in state.halls]
    return [[min(island, key=lambda ind: ind.fitness.values[0])] for island in state.islands]


def best_per_island(state: SearchState) -> list[Individual]:
    """Each island's best individual (Sec. 3.2.6): the first of its `top_per_island`."""
    return [top[0] for top in top_per_island(state)]


# -- checkpoints -----------------------------------------------------------------------------------------


def save_state(
    path: str | Path, state: SearchState, params: SearchParams, job: Mapping[str, Any] | None = None
) -> None:
    """The state as JSON, written atomically: every individual as prefix text with its fitness, the RNG
    state, the generation, the history, the parameters (checked on load) and `job` (what the caller
    records of the job that wrote it: its config's digest and MLflow run; read back by `saved_job`)."""
    version, internal, gauss = state.random_state
    atomic_write_json(
        path,
        {
            "format": STATE_FORMAT,
            "job": dict(job or {}),
            "params": asdict(params),
            "generation": state.generation,
            "random_state": [version, list(internal), gauss],
            "islands": [[[str(ind), ind.fitness.values[0]] for ind in island] for island in state.islands],
            "history": state.history,
        }
        | (
            {}
            if state.halls is None
            else {"halls": [[[str(ind), ind.fitness.values[0]] for ind in hall] for hall in state.halls]}
        ),
    )


#: The rules of the searches before `vector_pairs` ... `color_variance` existed, which their checkpoints hold
#: (the defaults then; the thesis's rules are the defaults now).
PRE_OPTION_RULES = {
    "vector_pairs": "mixed",
    "crossover_points": "type_first",
    "shares_count": "draws",
    "max_constants": None,
    "hall_of_fame": 0,
    "color_variance": False,
}


def _read_state(path: Path) -> Any:
    """The JSON `save_state` wrote at `path`; a one-line DataError when it cannot be read."""
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DataError(f"{path}: not a readable search checkpoint ({err})".replace("\n", " ")) from None


def saved_job(path: str | Path) -> dict[str, Any]:
    """The `job` entry `save_state` wrote in the checkpoint at `path` ({} when it has none)."""
    data = _read_state(Path(path))
    return dict(data.get("job") or {}) if isinstance(data, dict) else {}


def load_state(path: str | Path, params: SearchParams, pset: gp.PrimitiveSetTyped = PSET) -> SearchState:
    """A state `save_state` wrote, for a search with the same `params` (a one-line DataError otherwise)."""
    path = Path(path)
    data = _read_state(path)
    if not isinstance(data, dict) or data.get("format") != STATE_FORMAT:
        raise DataError(f"{path}: not a search checkpoint (format {STATE_FORMAT} expected)")
    # A checkpoint written before a parameter existed searched by that parameter's first default.
    defaults = json.loads(json.dumps(asdict(SearchParams()))) | PRE_OPTION_RULES
    saved = {k: v for k, v in (defaults | data["params"]).items() if k not in RESULT_FREE}
    wanted = {k: v for k, v in json.loads(json.dumps(asdict(params))).items() if k not in RESULT_FREE}
    if saved != wanted:
        diff = sorted(k for k in wanted if saved.get(k) != wanted[k])
        raise DataError(f"{path}: written by a search with other parameters ({', '.join(diff)})")

    def individuals(rows):
        members = []
        for text, value in rows:
            ind = Individual(parse(text, pset))
            ind.fitness.values = (float(value),)
            members.append(ind)
        return members

    islands = [individuals(island) for island in data["islands"]]
    halls = None
    if params.hall_of_fame > 0:
        if "halls" not in data:
            raise DataError(f"{path}: holds no halls of fame (hall_of_fame={params.hall_of_fame} expected)")
        halls = []
        for rows in data["halls"]:  # restored as saved: best first, ties in their saved order
            hall = tools.HallOfFame(params.hall_of_fame)
            hall.items = individuals(rows)
            hall.keys = [ind.fitness for ind in reversed(hall.items)]
            halls.append(hall)
    version, internal, gauss = data["random_state"]
    return SearchState(
        islands, int(data["generation"]), (version, tuple(internal), gauss), data["history"], halls
    )
