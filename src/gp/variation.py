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

Crossover, two rules (`crossover_points`):

    type_first  DEAP's `gp.cxOnePoint` (a type common to both parents, then a point of that type in each)
                with one change: the common types are sorted by name, since DEAP draws from a `set` of type
                objects, whose order follows their memory addresses and so differs between processes (a
                resumed run would diverge). Drawing the type first makes a vector-leaf exchange as likely as
                a scalar one (about half of all crossovers swap one feature leaf). nrbench's first rule,
                kept as an ablation.
    thesis      Sec. 3.2.4: a uniform point in each parent (never the root, as DEAP), both drawn again until
                they are "interchangeable" (both vector nodes or both scalar nodes); `cx_thesis`. The
                default.

Vector operands (`vector_pairs`): the thesis writes every vector term as a norm of ONE feature's
difference between the centre p and the neighbour q, ||f_p - f_q|| (Sec. 3.2.1.1, Fig. 3.2, Eq. 4.1-4.8);
the typed grammar lets the two operands differ ("mixed": feature a at p against feature b at q, nrbench's
first rule, kept as an ablation). With "same" (the default), every operator that puts a vector terminal
under a vector operator (replace, insert, swap, crossover) puts the same terminal in its sibling too
(`pair_leaves`), so a pair of one feature stays one and the search never makes a mixed pair; the random
draws are the same as under "mixed".

Constants: the thesis restricts "the number of constants" so that the replace mutation, which draws
variables and constants uniformly, does not mostly draw constants (Sec. 3.2.1.2, "Constants"), and names
the representative ones in Fig. 3.2. That is a restriction of the constant SET, which the grammar follows
with Fig. 3.2's twelve values (`src.gp.grammar.CONSTANTS`; replace draws among them and the variables
alike). A cap per expression (`max_constants`: a child with more constant leaves, numbers and pi, is
replaced by its parent, as the length limit does, `gp.staticLimit`) is an extra setting the thesis does
not state, off by default.

Every draw comes from Python's global `random` (as DEAP's), which the search seeds and checkpoints.
"""

from __future__ import annotations

import random
from collections.abc import Iterable, Mapping, Sequence

from deap import gp

from src.gp.grammar import ALL_VARIABLES, KERNELS, PSET, Vector
from src.gp.text import constant, parse

#: The mutation kinds of Sec. 3.2.4 (`SearchParams.mutation_kinds` weighs them).
MUTATION_KINDS = ("insert", "replace", "swap", "delete")
#: The crossover rules (`SearchParams.crossover_points`, module docstring).
CROSSOVER_RULES = ("type_first", "thesis")
#: What a vector operator's two operands may be (`SearchParams.vector_pairs`, module docstring).
VECTOR_PAIRS = ("mixed", "same")


def count_constants(tree: gp.PrimitiveTree) -> int:
    """Constant leaves of a tree: float terminals that are not variables (numbers, pi)."""
    return sum(1 for node in tree if node.arity == 0 and node.ret is float and node.name not in ALL_VARIABLES)


def mixed_pairs(tree: gp.PrimitiveTree) -> int:
    """Vector operators of a tree whose two operands are different features."""
    return sum(
        1
        for i, node in enumerate(tree)
        if node.arity == 2 and node.args[0] is Vector and tree[i + 1].name != tree[i + 2].name
    )


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


def pair_leaves(tree: gp.PrimitiveTree, index: int) -> None:
    """Under `vector_pairs: same`: when tree[index] is a vector terminal, its vector operator's other
    operand becomes the same terminal (module docstring)."""
    if tree[index].ret is not Vector:
        return
    parent = _parent(tree, index)
    other = parent + 2 if index == parent + 1 else parent + 1
    tree[other] = tree[index]


def type_first_points(ind1: gp.PrimitiveTree, ind2: gp.PrimitiveTree) -> tuple[int, int] | None:
    """The crossover points of `gp.cxOnePoint` (non-root): a type common to both parents (the common
    types sorted by name, module docstring), then a uniform point of that type in each; None when the
    parents have no common type or one is a single node."""
    if len(ind1) < 2 or len(ind2) < 2:
        return None
    types1: dict[type, list[int]] = {}
    types2: dict[type, list[int]] = {}
    for idx, node in enumerate(ind1[1:], 1):
        types1.setdefault(node.ret, []).append(idx)
    for idx, node in enumerate(ind2[1:], 1):
        types2.setdefault(node.ret, []).append(idx)
    common = sorted(set(types1) & set(types2), key=lambda t: t.__name__)
    if not common:
        return None
    type_ = random.choice(common)
    return random.choice(types1[type_]), random.choice(types2[type_])


def thesis_points(ind1: gp.PrimitiveTree, ind2: gp.PrimitiveTree) -> tuple[int, int] | None:
    """The thesis's crossover points (Sec. 3.2.4; uniform, Sec. 3.2.6): a uniform non-root point in each
    parent, both drawn again until they are "interchangeable" (the same type, vector or scalar); None when
    no such pair exists."""
    if len(ind1) < 2 or len(ind2) < 2:
        return None
    if not {n.ret for n in ind1[1:]} & {n.ret for n in ind2[1:]}:
        return None
    while True:
        i, j = random.randrange(1, len(ind1)), random.randrange(1, len(ind2))
        if ind1[i].ret is ind2[j].ret:
            return i, j


def _exchange(ind1, ind2, points: tuple[int, int] | None, same_pairs: bool):
    """The subtrees at `points` trade places; with `same_pairs` an exchanged vector leaf takes its
    sibling along (`pair_leaves`)."""
    if points is not None:
        i, j = points
        slice1, slice2 = ind1.searchSubtree(i), ind2.searchSubtree(j)
        ind1[slice1], ind2[slice2] = ind2[slice2], ind1[slice1]
        if same_pairs and ind1[i].ret is Vector:
            pair_leaves(ind1, i)
            pair_leaves(ind2, j)
    return ind1, ind2


def cx_one_point(ind1: gp.PrimitiveTree, ind2: gp.PrimitiveTree, same_pairs: bool = False):
    """`gp.cxOnePoint` with its common types in a fixed order (`type_first_points`); typed: a subtree is
    only exchanged for one of the same type. `same_pairs`: an exchanged vector leaf takes its sibling
    along (`pair_leaves`)."""
    return _exchange(ind1, ind2, type_first_points(ind1, ind2), same_pairs)


def cx_thesis(ind1: gp.PrimitiveTree, ind2: gp.PrimitiveTree, same_pairs: bool = False):
    """The thesis's crossover (Sec. 3.2.4) at `thesis_points`; parents without a common type are returned
    unchanged. `same_pairs`: an exchanged vector leaf takes its sibling along (`pair_leaves`)."""
    return _exchange(ind1, ind2, thesis_points(ind1, ind2), same_pairs)


def mut_insert(
    individual: gp.PrimitiveTree, book: Mapping[type, Sequence[list]], pset, same_pairs: bool = False
):
    """Insert (Sec. 3.2.4): DEAP's `gp.mutUniform` (written out, same draws) with a generator that draws
    a codebook sub-expression of the point's type uniformly (the codebook must hold both types, which
    `codebook` of any feature does). `same_pairs`: an inserted vector leaf takes its sibling along."""
    index = random.randrange(len(individual))
    slice_ = individual.searchSubtree(index)
    type_ = individual[index].ret
    individual[slice_] = list(random.choice(book[type_]))
    if same_pairs:
        pair_leaves(individual, index)
    return (individual,)


def mut_replace(individual: gp.PrimitiveTree, pset, same_pairs: bool = False):
    """Replace (Sec. 3.2.4): DEAP's `gp.mutNodeReplacement` (written out, same draws; never the root, as
    DEAP does). `same_pairs`: a replaced vector leaf takes its sibling along."""
    if len(individual) < 2:
        return (individual,)
    index = random.randrange(1, len(individual))
    node = individual[index]
    if node.arity == 0:
        term = random.choice(pset.terminals[node.ret])
        if type(term) is gp.MetaEphemeral:
            term = term()
        individual[index] = term
        if same_pairs:
            pair_leaves(individual, index)
    else:
        prims = [p for p in pset.primitives[node.ret] if p.args == node.args]
        individual[index] = random.choice(prims)
    return (individual,)


def _disjoint(a: slice, b: slice) -> bool:
    return a.stop <= b.start or b.stop <= a.start


def mut_swap(individual: gp.PrimitiveTree, tries: int = 20, same_pairs: bool = False):
    """Swap (Sec. 3.2.4): two type-compatible, non-overlapping subtrees of one tree trade places; the
    points are drawn again (up to `tries` times) while they are not interchangeable. `same_pairs`: two
    swapped vector leaves take their siblings along."""
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
        if same_pairs and individual[i].ret is Vector:
            pair_leaves(individual, i)
            pair_leaves(individual, j)
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
    weights, typed crossover by `crossover_points`, vector operands by `vector_pairs`, and the length limit
    `max_length` (and the cap `max_constants`, when set) on both (`gp.staticLimit`: a child over a limit is
    replaced by its parent)."""

    def __init__(
        self,
        mutation_kinds: Mapping[str, float],
        max_length: int,
        pset: gp.PrimitiveSetTyped,
        book: Mapping[type, Sequence[list]],
        crossover_points: str = "type_first",
        vector_pairs: str = "mixed",
        max_constants: int | None = None,
    ):
        if crossover_points not in CROSSOVER_RULES:
            raise ValueError(
                f"crossover_points={crossover_points!r}: expected one of {list(CROSSOVER_RULES)}"
            )
        if vector_pairs not in VECTOR_PAIRS:
            raise ValueError(f"vector_pairs={vector_pairs!r}: expected one of {list(VECTOR_PAIRS)}")
        self.pset, self.book = pset, book
        self.same_pairs = vector_pairs == "same"
        kinds = [(k, float(w)) for k, w in mutation_kinds.items() if w > 0]
        self.kinds = [k for k, _ in kinds]
        self.weights = [w for _, w in kinds]
        self._cx = cx_thesis if crossover_points == "thesis" else cx_one_point
        mutate, mate = self._mutate, self._mate
        if max_constants is not None:  # inner: a child over the cap is its parent before the length check
            cap = gp.staticLimit(key=count_constants, max_value=int(max_constants))
            mutate, mate = cap(mutate), cap(mate)
        limit = gp.staticLimit(key=len, max_value=max_length)
        self.mutate = limit(mutate)
        self.mate = limit(mate)

    def _mate(self, ind1, ind2):
        return self._cx(ind1, ind2, same_pairs=self.same_pairs)

    def _mutate(self, individual):
        kind = random.choices(self.kinds, weights=self.weights)[0]
        if kind == "insert":
            return mut_insert(individual, self.book, self.pset, self.same_pairs)
        if kind == "replace":
            return mut_replace(individual, self.pset, self.same_pairs)
        if kind == "swap":
            return mut_swap(individual, same_pairs=self.same_pairs)
        return mut_delete(individual, self.pset)
