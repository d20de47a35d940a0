"""The genetic-programming search for filter weight expressions (Davletaliyev 2016, Sec. 3.2.3-3.2.6), on
DEAP's operators.

    population  `islands` islands of `population` individuals each (the island model, Sec. 3.2.5), seeded
                only from the bilateral filter: `seed_copies` (10%) copies of it, the rest one mutation
                of it each (Sec. 3.2.5, "Initial Population")
    generation  per island, a whole new population of the same size (Sec. 3.2.6): each new individual is
                a replication (10%: a tournament winner, unchanged), a crossover (45%: two winners,
                `cx_one_point`, both children kept, each then mutated with probability 0.85) or a
                mutation (45%: one winner, `mutate`); tournaments of 8 (`tools.selTournament`; lowest
                fitness wins); every child longer than `max_length` (75 nodes) is replaced by its parent
                (`gp.staticLimit`)
    migration   every `migration_interval` (5) generations a copy of each island's best replaces the worst
                of the next island, i -> (i + 1) mod n (`tools.migRing`, Sec. 3.2.5)
    fitness     mean over the training images of relMSE(filtered) / relMSE(noisy), relMSE of Eq. 3.5
                (its m/2 factor cancels in the ratio); an undefined expression (NaN/Inf weights or a zero
                weight sum on any image) gets the worst fitness, `WORST` = the largest float (Sec. 3.2.3)
    result      the best individual of each island (Sec. 3.2.6, "Top expressions from every island")

Mutations (Sec. 3.2.4; their kind drawn with `mutation_kinds`, 30/30/30/10 in the thesis), points uniform
over all nodes (Sec. 3.2.6):

    insert   the subtree at a point becomes a sub-expression of the same type drawn uniformly from the
             codebook (`codebook`, Sec. 3.2.2): `gp.mutUniform` with the codebook as its generator (DEAP's
             own `gp.mutInsert` inserts a *new* primitive above the point, which is not the thesis's insert)
    replace  one node becomes an equivalent one (same argument types; a terminal any terminal of its type,
             constants and variables alike): `gp.mutNodeReplacement`
    swap     two type-compatible, disjoint subtrees of one tree trade places (`mut_swap`: DEAP has no
             in-tree swap)
    delete   the subtree at a point becomes the constant 1.0; at a vector terminal, its vector operator's
             subtree does (`mut_delete`: DEAP's `gp.mutShrink` hoists a child instead, not the thesis's)

Crossover is DEAP's `gp.cxOnePoint` (a type common to both parents, then a point of that type in each)
with one change: the common types are sorted by name, since DEAP draws from a `set` of type objects, whose
order follows their memory addresses and so differs between processes (a resumed run would diverge).

Determinism: DEAP and `src.gp.grammar` draw from Python's global `random`; `GPSearch` seeds it with
`params.seed` at the start and saves `random.getstate()` after every generation, restoring it before the
next, so a run is reproducible and a run resumed from its checkpoint (`save_state` / `load_state`, written
atomically after each generation) gives the same generations as the uninterrupted run.
"""

from __future__ import annotations

import copy
import json
import math
import random
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch
from deap import base, gp, tools

from src.errors import DataError
from src.gp.evaluate import filter_images
from src.gp.grammar import KERNELS, PSET, VARIABLES, VECTORS, Vector
from src.gp.text import constant, parse, to_infix
from src.io.atomic import atomic_write_json

WORST = sys.float_info.max
"""Fitness of an undefined expression (Davletaliyev 2016, Sec. 3.2.3: "maximum float")."""

MUTATION_KINDS = ("insert", "replace", "swap", "delete")
STATE_FORMAT = "nrbench-gp-search-v1"


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

    def __post_init__(self) -> None:
        total = self.replication + self.crossover + self.mutation
        if abs(total - 1.0) > 1e-6:
            raise ValueError(f"replication + crossover + mutation = {total:g}; expected 1")
        unknown = set(self.mutation_kinds) - set(MUTATION_KINDS)
        if unknown:
            raise ValueError(f"unknown mutation kind(s) {sorted(unknown)}; expected some of {MUTATION_KINDS}")
        if not sum(self.mutation_kinds.values()) > 0:
            raise ValueError("mutation_kinds: the weights must not all be 0")


# -- grammar restricted to the data ---------------------------------------------------------------------


def search_pset(available: Iterable[str]) -> gp.PrimitiveSetTyped:
    """The grammar (`PSET`) with only the vector terminals and variables in `available` (plus `pixel`,
    always computable): the operators draw terminals from it, so no individual reads a feature the data
    lack. Constants and operators are all kept."""
    keep = set(available) | {"pixel"}
    pset = copy.deepcopy(PSET)
    drop = [n for n in (*VECTORS, *VARIABLES) if n not in keep]
    for type_ in (Vector, float):
        pset.terminals[type_] = [t for t in pset.terminals[type_] if t.name not in drop]
    pset.terms_count -= len(drop)
    if not pset.terminals[Vector]:
        raise ValueError("search grammar: no vector terminal available")
    return pset


# -- codebook (Sec. 3.2.2) -----------------------------------------------------------------------------


def kernel_expressions(features: Iterable[str]) -> list[str]:
    """The analytic filters the codebook is made from (Davletaliyev 2016, Sec. 3.2.2): each kernel
    (mitchell, sinc, epanechnikov, biweight, tricube) of each feature's distance ||f_i - f_j||, and the
    Gaussian of it with sigma 0.1, exp(-||f_i - f_j||^2 / (2 * 0.1^2)) (the thesis's own example)."""
    out = []
    for f in features:
        out += [f"{k}(distance2({f}, {f}))" for k in KERNELS]
        out.append(f"exp(-(distance2({f}, {f}) ** 2.0 / (2.0 * 0.1 ** 2.0)))")
    return out


def codebook(expressions: Iterable[str], pset: gp.PrimitiveSetTyped = PSET) -> dict[type, list[list]]:
    """Every distinct sub-expression of `expressions`, by return type (float, Vector), each as its list of
    nodes, in first-seen order (Sec. 3.2.2: "union of the sub-expressions")."""
    seen: dict[str, tuple[type, list]] = {}
    for text in expressions:
        tree = parse(text, pset)
        for i in range(len(tree)):
            nodes = tree[tree.searchSubtree(i)]
            key = str(gp.PrimitiveTree(nodes))
            seen.setdefault(key, (tree[i].ret, list(nodes)))
    book: dict[type, list[list]] = {float: [], Vector: []}
    for type_, nodes in seen.values():
        book[type_].append(nodes)
    return book


# -- variation operators ---------------------------------------------------------------------------------


def cx_one_point(ind1: gp.PrimitiveTree, ind2: gp.PrimitiveTree):
    """`gp.cxOnePoint` with its common types in a fixed order (module docstring); typed: a subtree is only
    exchanged for one of the same type."""
    if len(ind1) < 2 or len(ind2) < 2:
        return ind1, ind2
    types1: dict[type, list[int]] = {}
    types2: dict[type, list[int]] = {}
    for idx, node in enumerate(ind1[1:], 1):
        types1.setdefault(node.ret, []).append(idx)
    for idx, node in enumerate(ind2[1:], 1):
        types2.setdefault(node.ret, []).append(idx)
    common = sorted(set(types1) & set(types2), key=lambda t: t.__name__)
    if common:
        type_ = random.choice(common)
        slice1 = ind1.searchSubtree(random.choice(types1[type_]))
        slice2 = ind2.searchSubtree(random.choice(types2[type_]))
        ind1[slice1], ind2[slice2] = ind2[slice2], ind1[slice1]
    return ind1, ind2


def mut_insert(individual: gp.PrimitiveTree, book: Mapping[type, Sequence[list]], pset):
    """Insert (Sec. 3.2.4): DEAP's `gp.mutUniform` with a generator that draws a codebook sub-expression
    of the point's type uniformly (the codebook must hold both types, which `codebook` of any feature
    does)."""

    def draw(pset, type_):
        return list(random.choice(book[type_]))

    return gp.mutUniform(individual, draw, pset)


def mut_replace(individual: gp.PrimitiveTree, pset):
    """Replace (Sec. 3.2.4): DEAP's `gp.mutNodeReplacement` (never the root, as DEAP does)."""
    return gp.mutNodeReplacement(individual, pset)


def _disjoint(a: slice, b: slice) -> bool:
    return a.stop <= b.start or b.stop <= a.start


def mut_swap(individual: gp.PrimitiveTree, tries: int = 20):
    """Swap (Sec. 3.2.4): two type-compatible, non-overlapping subtrees of one tree trade places; the
    points are drawn again (up to `tries` times) while they are not interchangeable."""
    n = len(individual)
    for _ in range(tries):
        i, j = random.randrange(n), random.randrange(n)
        if individual[i].ret is not individual[j].ret:
            continue
        si, sj = individual.searchSubtree(i), individual.searchSubtree(j)
        if not _disjoint(si, sj):
            continue
        if si.start > sj.start:
            si, sj = sj, si
        nodes = list(individual)
        individual[0 : len(nodes)] = (
            nodes[: si.start] + nodes[sj] + nodes[si.stop : sj.start] + nodes[si] + nodes[sj.stop :]
        )
        break
    return (individual,)


def _parent(tree: gp.PrimitiveTree, index: int) -> int:
    """Index of the node whose argument tree[index] is (index > 0)."""
    stack: list[list[int]] = []  # [node index, arguments still to read]
    for i, node in enumerate(tree):
        if i == index:
            return stack[-1][0]
        if stack:
            stack[-1][1] -= 1
        while stack and stack[-1][1] == 0:
            stack.pop()
        if node.arity:
            stack.append([i, node.arity])
    raise IndexError(index)


def mut_delete(individual: gp.PrimitiveTree, pset):
    """Delete (Sec. 3.2.4): the subtree at a uniform point becomes the constant 1.0; a vector node's
    vector operator is replaced instead."""
    index = random.randrange(len(individual))
    if individual[index].ret is Vector:
        index = _parent(individual, index)
    individual[individual.searchSubtree(index)] = [constant(1.0, pset)]
    return (individual,)


class Variation:
    """The mutation and crossover of one search: a mutation of a drawn kind, typed crossover, and the
    length limit on both (`gp.staticLimit`: a child over the limit is replaced by its parent)."""

    def __init__(self, params: SearchParams, pset: gp.PrimitiveSetTyped, book: Mapping[type, Sequence[list]]):
        self.params, self.pset, self.book = params, pset, book
        kinds = [(k, float(w)) for k, w in params.mutation_kinds.items() if w > 0]
        self.kinds = [k for k, _ in kinds]
        self.weights = [w for _, w in kinds]
        limit = gp.staticLimit(key=len, max_value=params.max_length)
        self.mutate = limit(self._mutate)
        self.mate = limit(cx_one_point)

    def _mutate(self, individual):
        kind = random.choices(self.kinds, weights=self.weights)[0]
        if kind == "insert":
            return mut_insert(individual, self.book, self.pset)
        if kind == "replace":
            return mut_replace(individual, self.pset)
        if kind == "swap":
            return mut_swap(individual)
        return mut_delete(individual, self.pset)


# -- fitness ---------------------------------------------------------------------------------------------


def relative_error(x: torch.Tensor, y: torch.Tensor, eps: float) -> torch.Tensor:
    """Per image (N,): mean over pixels of sum over channels of (x - y)^2 / (y^2 + eps), i.e. Eq. 3.5
    (`src.metrics.image.relmse_spp`) without its m/2 factor, which cancels in the fitness ratio."""
    return ((x - y).square() / (y.square() + eps)).sum(1).flatten(1).mean(1)


class Fitness:
    """The thesis's fitness (Sec. 3.2.3) of many trees on fixed training images, `tree_batch` trees per
    `filter_images` call (they share features and common sub-expressions).

    `features`: terminal -> (N, C, H, W) as `src.gp.evaluate.filter_images` takes them; `color`,
    `reference`: (N, 3, H, W) linear HDR."""

    def __init__(
        self,
        features: Mapping[str, torch.Tensor],
        color: torch.Tensor,
        reference: torch.Tensor,
        radius: int,
        eps: float = 0.01,
        tree_batch: int = 16,
    ) -> None:
        self.features, self.color, self.reference = dict(features), color, reference
        self.radius, self.eps, self.tree_batch = int(radius), float(eps), int(tree_batch)
        self.noisy = relative_error(color, reference, self.eps)
        if not bool((self.noisy > 0).all()):
            raise DataError("search: a training image's noisy colour equals its reference (relMSE 0)")
        self.evaluations = 0

    def __call__(self, trees: Sequence[gp.PrimitiveTree]) -> list[float]:
        out: list[float] = []
        for start in range(0, len(trees), self.tree_batch):
            chunk = trees[start : start + self.tree_batch]
            result = filter_images(chunk, self.features, self.color, self.radius)
            for filtered, valid in zip(result.color, result.valid, strict=True):
                value = float((relative_error(filtered, self.reference, self.eps) / self.noisy).mean())
                out.append(value if bool(valid.all()) and math.isfinite(value) else WORST)
        self.evaluations += len(trees)
        return out


# -- the search ------------------------------------------------------------------------------------------


@dataclass
class SearchState:
    """Where a search is: its islands (evaluated), the generation they are, the RNG state to go on with,
    and the per-generation statistics so far."""

    islands: list[list[Individual]]
    generation: int
    random_state: tuple
    history: list[dict[str, Any]]


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
        self.variation = Variation(params, pset, book)
        self.clone = copy.deepcopy

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
        if not todo:
            return
        groups = list(todo.values())
        values = self.fitness([group[0] for group in groups])
        for group, value in zip(groups, values, strict=True):
            for ind in group:
                ind.fitness.values = (value,)

    def select(self, island: Sequence[Individual]) -> Individual:
        return self.clone(tools.selTournament(island, 1, tournsize=self.params.tournament_size)[0])

    def offspring(self, island: Sequence[Individual]) -> list[Individual]:
        """A new island of the same size (Sec. 3.2.6): replication, crossover (children mutated with
        `crossover_mutation`) or mutation, per new individual."""
        p, out = self.params, []
        while len(out) < len(island):
            r = random.random()
            if r < p.replication:
                out.append(self.select(island))
            elif r < p.replication + p.crossover:
                children = self.variation.mate(self.select(island), self.select(island))
                for child in children:
                    if random.random() < p.crossover_mutation:
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
        state = SearchState(islands, 0, random.getstate(), [])
        self._record(state, sum(len(i) for i in islands))
        return state

    def step(self, state: SearchState) -> SearchState:
        """The next generation of every island, evaluated, then migration when it is due."""
        random.setstate(state.random_state)
        islands = [self.offspring(island) for island in state.islands]
        fresh = [ind for island in islands for ind in island if not ind.fitness.valid]
        self.evaluate(fresh)
        generation = state.generation + 1
        if generation % self.params.migration_interval == 0:
            self.migrate(islands)
        new = SearchState(islands, generation, random.getstate(), list(state.history))
        self._record(new, len({str(ind) for ind in fresh}))
        return new

    def run(
        self,
        state: SearchState | None = None,
        checkpoint: str | Path | None = None,
        on_generation: Callable[[SearchState], None] | None = None,
    ) -> SearchState:
        """All `generations` from `state` (or from the start), saving `checkpoint` after each."""
        if state is None:
            state = self.start()
            if checkpoint is not None:
                save_state(checkpoint, state, self.params)
            if on_generation is not None:
                on_generation(state)
        while state.generation < self.params.generations:
            state = self.step(state)
            if checkpoint is not None:
                save_state(checkpoint, state, self.params)
            if on_generation is not None:
                on_generation(state)
        return state


def best_per_island(state: SearchState) -> list[Individual]:
    """Each island's best individual (Sec. 3.2.6), in island order (ties: the first)."""
    return [min(island, key=lambda ind: ind.fitness.values[0]) for island in state.islands]


# -- checkpoints -----------------------------------------------------------------------------------------


def save_state(path: str | Path, state: SearchState, params: SearchParams) -> None:
    """The state as JSON, written atomically: every individual as prefix text with its fitness, the RNG
    state, the generation, the history and the parameters (checked on load)."""
    version, internal, gauss = state.random_state
    atomic_write_json(
        path,
        {
            "format": STATE_FORMAT,
            "params": asdict(params),
            "generation": state.generation,
            "random_state": [version, list(internal), gauss],
            "islands": [[[str(ind), ind.fitness.values[0]] for ind in island] for island in state.islands],
            "history": state.history,
        },
    )


def load_state(path: str | Path, params: SearchParams, pset: gp.PrimitiveSetTyped = PSET) -> SearchState:
    """A state `save_state` wrote, for a search with the same `params` (a one-line DataError otherwise)."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DataError(f"{path}: not a readable search checkpoint ({err})".replace("\n", " ")) from None
    if not isinstance(data, dict) or data.get("format") != STATE_FORMAT:
        raise DataError(f"{path}: not a search checkpoint (format {STATE_FORMAT} expected)")
    saved = {k: v for k, v in data["params"].items() if k not in ("generations",)}
    wanted = {k: v for k, v in json.loads(json.dumps(asdict(params))).items() if k not in ("generations",)}
    if saved != wanted:
        diff = sorted(k for k in wanted if saved.get(k) != wanted[k])
        raise DataError(f"{path}: written by a search with other parameters ({', '.join(diff)})")
    islands = []
    for island in data["islands"]:
        members = []
        for text, value in island:
            ind = Individual(parse(text, pset))
            ind.fitness.values = (float(value),)
            members.append(ind)
        islands.append(members)
    version, internal, gauss = data["random_state"]
    return SearchState(islands, int(data["generation"]), (version, tuple(internal), gauss), data["history"])
