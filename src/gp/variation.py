"""The variation operators of the genetic-programming filter search (Davletaliyev 2016, Sec. 3.2.2 and
3.2.4), on DEAP's: the codebook the insert mutation draws from, the four mutations, the typed one-point
crossover, and `Variation`, which draws a mutation kind and applies the length limit to both.
`src.gp.search` drives them (the island model, Sec. 3.2.5-3.2.6).

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

Every draw comes from Python's global `random` (as DEAP's), which the search seeds and checkpoints.
"""

from __future__ import annotations

import random
from collections.abc import Iterable, Mapping, Sequence

from deap import gp

from src.gp.grammar import KERNELS, PSET, Vector
from src.gp.text import constant, parse

#: The mutation kinds of Sec. 3.2.4 (`SearchParams.mutation_kinds` weighs them).
MUTATION_KINDS = ("insert", "replace", "swap", "delete")


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


# -- operators ---------------------------------------------------------------------------------


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
    """The mutation and crossover of one search: a mutation of a kind drawn with the `mutation_kinds`
    weights, typed crossover, and the length limit `max_length` on both (`gp.staticLimit`: a child over
    the limit is replaced by its parent)."""

    def __init__(
        self,
        mutation_kinds: Mapping[str, float],
        max_length: int,
        pset: gp.PrimitiveSetTyped,
        book: Mapping[type, Sequence[list]],
    ):
        self.pset, self.book = pset, book
        kinds = [(k, float(w)) for k, w in mutation_kinds.items() if w > 0]
        self.kinds = [k for k, _ in kinds]
        self.weights = [w for _, w in kinds]
        limit = gp.staticLimit(key=len, max_value=max_length)
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
