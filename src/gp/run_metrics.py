"""What a finished filter search logs beyond its per-generation curve: the best fitness at the start and
halfway, and the feature terminals of its best expression, as run metrics the ledger can pair.

Davletaliyev 2016 measures the search's error as "the minimum of all relMSEs of expressions generated
during the optimization" (Sec. 4.2) and sees it decrease with the iterations (Figure 4.6); it counts the
features of the optimisations' results (Sec. 4.3, Figure 4.8: "the most frequently used feature is
normal"). The ledger compares one value per run, so both become run metrics here.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping, Sequence
from typing import Any

from src.gp.grammar import GRAMMAR_VECTORS, VARIABLES, VECTORS

#: The features counted in an expression: every vector terminal but the pixel position, and the scalar
#: variables (the noisy colour's and the grammar's).
COUNTED_FEATURES = tuple(v for v in VECTORS if v != "pixel") + VARIABLES
#: The feature Figure 4.8 finds most used, and the features it is ranked against: Fig. 3.2's vector
#: terminals. The noisy colour is left out: it is the seed expression's range term, not one of the
#: grammar's features, so every expression inherits it.
LEADING_FEATURE = "normal"
RIVALS = tuple(v for v in GRAMMAR_VECTORS if v != LEADING_FEATURE)


def best_through(history: Sequence[Mapping[str, Any]], generation: int) -> float:
    """The minimum fitness of every island over the generations up to and including `generation` (the
    thesis's Sec. 4.2 measure, `search_best_so_far` at that step). `history`: the search's records, each
    with its `generation` and per island its `best`."""
    bests = [i["best"] for record in history if record["generation"] <= generation for i in record["islands"]]
    if not bests:
        raise ValueError(f"no search record at or before generation {generation}")
    return min(bests)


def feature_counts(expression: str) -> Counter[str]:
    """How often each feature terminal (`COUNTED_FEATURES`) occurs in an expression, as tree nodes:
    `distance2(depth, depth)` counts depth twice."""
    from deap import gp

    from src.gp.text import parse

    features = set(COUNTED_FEATURES)
    nodes = parse(expression)
    return Counter(str(n.value) for n in nodes if isinstance(n, gp.Terminal) and n.value in features)


def search_run_metrics(history: Sequence[Mapping[str, Any]], best_expression: str) -> dict[str, float]:
    """The finished search's run metrics:

    - `search_best_initial`: the best fitness of generation 0 (the seeded population);
    - `search_best_midway`: the best so far at generation floor(G / 2), G the last generation;
    - `search_feature_<name>`: occurrences of each counted feature in the best expression (0 if absent);
    - `search_feature_top_rival`: the most occurrences of one of `RIVALS` (what normal is ranked against).
    """
    last = max(record["generation"] for record in history)
    counts = feature_counts(best_expression)
    metrics = {
        "search_best_initial": best_through(history, 0),
        "search_best_midway": best_through(history, last // 2),
    }
    metrics |= {f"search_feature_{name}": float(counts[name]) for name in COUNTED_FEATURES}
    metrics["search_feature_top_rival"] = float(max(counts[name] for name in RIVALS))
    return metrics
