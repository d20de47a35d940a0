"""The thesis's search rules as options of the GP search (Davletaliyev 2016, Sec. 3.2.1-3.2.6; issue 32),
each pinned by its measured statistic on seeded islands of the cross-bilateral seed: vector pairs of one
feature, the uniform-point crossover, expansion shares that count individuals, the constant cap, the
colour-variance terminal, the hall of fame and the fitness cache. Fast: a text-hash fitness stands in for
image filtering except where the cache must leave real fitness values unchanged."""

import random

import pytest
import torch

from src.gp.fitness import Fitness
from src.gp.search import GPSearch, Individual, SearchParams, best_per_island, load_state
from src.gp.text import parse
from src.gp.variation import (
    count_constants,
    cx_one_point,
    cx_thesis,
    mixed_pairs,
    thesis_points,
    type_first_points,
)
from tests.test_gp_search import (
    SEED,
    _images,
    _pset_book,
    _search,
    _text_fitness,
    _TextFitness,
    _texts,
    _within,
)

# -- vector pairs ---------------------------------------------------------------------------------------


def _population(params, generations=6, seed=0):
    """Every individual of a text-fitness search after `generations` (cheap: no image filtering)."""
    params = SearchParams(**{**params.__dict__, "generations": generations, "seed": seed})
    state = GPSearch(_TextFitness(), SEED, params, *_pset_book()).run()
    return [ind for island in state.islands for ind in island]


def _vector_ops(trees):
    return sum(1 for t in trees for node in t if node.arity == 2 and node.args[0].__name__ == "Vector")


def test_same_pairs_leave_no_mixed_pair_in_a_large_seeded_population():
    """Under `same` no operator makes a mixed pair: 0 in 2 x 150 individuals after 6 generations of every
    mutation kind and crossover; under `mixed` (the ablation) the same search has many."""
    base = SearchParams(islands=2, population=150)
    same = _population(base)  # the default
    mixed = _population(SearchParams(**{**base.__dict__, "vector_pairs": "mixed"}))
    assert _vector_ops(same) > 1000  # the population is full of vector operators
    assert sum(mixed_pairs(t) for t in same) == 0
    share = sum(mixed_pairs(t) for t in mixed) / _vector_ops(mixed)
    assert share > 0.05, share


@pytest.mark.parametrize("kind", ["insert", "replace", "swap"])
def test_each_mutation_under_same_pairs_changes_a_pair_as_one(kind):
    """Each mutation that can put a vector leaf under a vector operator, 400 times on the seed under
    `same`: no mixed pair, and some children read a feature the seed does not (the pair did change)."""
    params = SearchParams(mutation_kinds={kind: 1.0}, vector_pairs="same")
    search = GPSearch(_TextFitness(), SEED, params, *_pset_book())
    random.seed(1)
    seed_features = {n.name for n in search.seed if n.ret.__name__ == "Vector"}
    new_features = 0
    for _ in range(400):
        (child,) = search.variation.mutate(search.clone(search.seed))
        assert mixed_pairs(child) == 0, str(child)
        new_features += bool({n.name for n in child if n.ret.__name__ == "Vector"} - seed_features)
    if kind != "swap":  # swap only moves the seed's own features; nGradient is the one feature not in the
        assert new_features > 5  # seed (replace: about 400 x 10/40 x 1/6 = 17 children read it)


def test_same_pairs_swaps_the_two_features_of_two_pairs():
    """Crossover of two vector leaves under `same`: each pair takes the other's feature, both operands."""
    a = Individual(parse("distance2(normal, normal) + 1.0"))
    b = Individual(parse("distance1(depth, depth) * 2.0"))
    random.seed(0)
    for _ in range(50):
        x, y = Individual(a), Individual(b)
        cx_thesis(x, y, same_pairs=True)
        if str(x) == "add(distance2(depth, depth), 1.0)":
            assert str(y) == "mul(distance1(normal, normal), 2.0)"
            break
    else:
        pytest.fail("no vector-leaf exchange in 50 crossovers")
    x, y = Individual(a), Individual(b)
    random.seed(0)
    cx_thesis(x, y, same_pairs=False)  # the same draws without the rule: a mixed pair somewhere, or none
    assert mixed_pairs(x) + mixed_pairs(y) in (0, 2)


# -- crossover ------------------------------------------------------------------------------------------


def _kinds(tree):
    """(vector, scalar) counts of the non-root nodes: the crossover's candidate points."""
    vector = sum(1 for n in tree[1:] if n.ret.__name__ == "Vector")
    return vector, len(tree) - 1 - vector


def test_leaf_swap_share_of_each_crossover_rule_on_a_seeded_island():
    """The share of crossovers that exchange one feature leaf (a Vector point), 4000 draws between
    tournament-free random pairs of a seeded island of 100: type-first draws the type first, so about half
    (0.5 for parents with both types); the thesis's rule draws uniform points until both are of one kind,
    P(vector) = v1 v2 / (v1 v2 + s1 s2) per pair, about 10 % for the bilateral seed (10 vector leaves among
    40 non-root nodes), near the thesis's 9 %. Each count is within 4 sigma of the sum of the per-pair
    probabilities."""
    search = _search(SearchParams(islands=1, population=100))
    random.seed(4)
    island = search.seeded_island()
    for points, exact in (
        (type_first_points, lambda v1, s1, v2, s2: 0.5),
        (thesis_points, lambda v1, s1, v2, s2: v1 * v2 / (v1 * v2 + s1 * s2)),
    ):
        rng, n, leaf, expected, var = random.Random(7), 4000, 0, 0.0, 0.0
        random.seed(11)
        for _ in range(n):
            a, b = rng.choice(island), rng.choice(island)
            (v1, s1), (v2, s2) = _kinds(a), _kinds(b)
            if not (v1 and v2 or s1 and s2):  # no common kind (a deleted root): no crossover
                assert points(a, b) is None
                continue
            i, j = points(a, b)
            assert a[i].ret is b[j].ret
            leaf += a[i].ret.__name__ == "Vector"
            p = exact(v1, s1, v2, s2) if v1 and v2 and s1 and s2 else float(bool(v1 and v2))
            expected, var = expected + p, var + p * (1 - p)
        assert abs(leaf - expected) <= 4 * var**0.5, (points.__name__, leaf / n, expected / n)
        if points is thesis_points:
            assert 0.07 < leaf / n < 0.13
        else:
            assert 0.45 < leaf / n < 0.55


def test_thesis_points_are_uniform_over_the_compatible_pairs():
    """`neg(distance2(normal, depth))` x `add(distance1(color, color), 2.0)` (non-root points: 1 scalar + 2
    vector, and 2 scalar + 2 vector): the compatible pairs are 1 x 2 scalar and 2 x 2 vector, under the
    thesis's rule each of the 6 equally likely; type-first gives each kind 1/2, so a scalar pair 1/4 and a
    vector pair 1/8 (4000 draws each; 4 sigma)."""
    a = Individual(parse("neg(distance2(normal, depth))"))
    b = Individual(parse("distance1(color, color) + 2.0"))
    random.seed(3)
    n = 4000
    for points, p_pair in (
        (thesis_points, {"s": 1 / 6, "v": 1 / 6}),
        (type_first_points, {"s": 1 / 4, "v": 1 / 8}),
    ):
        counts: dict[tuple[int, int], int] = {}
        for _ in range(n):
            pair = points(a, b)
            counts[pair] = counts.get(pair, 0) + 1
        assert len(counts) == 6
        for (i, j), count in counts.items():
            kind = "v" if a[i].ret.__name__ == "Vector" else "s"
            assert _within(count, n, p_pair[kind]), (points.__name__, (i, j), count)


def test_crossover_without_a_common_kind_changes_nothing():
    a = Individual(parse("distance2(normal, normal)"))  # non-root: vector leaves only
    b = Individual(parse("neg(2.0)"))  # non-root: one scalar
    for cx in (cx_thesis, cx_one_point):
        x, y = cx(Individual(a), Individual(b))
        assert (str(x), str(y)) == (str(a), str(b))


# -- expansion shares -----------------------------------------------------------------------------------


def _origins(params, monkeypatch, n=1000, rounds=20):
    """Counts of new individuals by origin over `rounds` offspring islands of n (crossover children not
    mutated): r replication, x crossover child, m mutation."""
    search = GPSearch(_TextFitness(), SEED, params, *_pset_book())

    def tagged(origin):
        ind = Individual(parse("1.0"))
        ind.origin = origin
        return ind

    monkeypatch.setattr(search, "select", lambda island: tagged("r"))
    monkeypatch.setattr(search.variation, "mate", lambda a, b: (tagged("x"), tagged("x")))
    monkeypatch.setattr(search.variation, "mutate", lambda a: (tagged("m") if a.origin == "r" else a,))
    random.seed(5)
    counts = dict.fromkeys("rxm", 0)
    island = [tagged("r") for _ in range(n)]
    for _ in range(rounds):
        for ind in search.offspring(island):
            counts[ind.origin] += 1
    return counts, n * rounds


def test_expansion_split_counts_draws_or_individuals(monkeypatch):
    """10/45/45 % per draw gives 0.10 : 0.90 : 0.45 individuals = 6.9/62.1/31.0 % (the ablation, nrbench's
    first rule); counting individuals gives 10/45/45 % of them (20 islands of 1000; 4 sigma)."""
    for count, shares in (
        ("draws", {"r": 0.10 / 1.45, "x": 0.90 / 1.45, "m": 0.45 / 1.45}),
        ("individuals", {"r": 0.10, "x": 0.45, "m": 0.45}),
    ):
        params = SearchParams(shares_count=count, crossover_mutation=0.0)
        counts, total = _origins(params, monkeypatch)
        assert sum(counts.values()) == total
        for origin, p in shares.items():
            assert _within(counts[origin], total, p), (count, counts)


def test_draw_weights_by_value():
    assert SearchParams(shares_count="draws").draw_weights() == (0.10, 0.45, 0.45)
    r, c, m = SearchParams().draw_weights()  # the default: individuals
    assert (r, c, m) == pytest.approx((0.1 / 0.775, 0.225 / 0.775, 0.45 / 0.775))
    with pytest.raises(ValueError, match="shares_count='children'"):
        SearchParams(shares_count="children")


# -- constant cap ---------------------------------------------------------------------------------------


def test_constant_cap_is_never_exceeded():
    """6 generations of 2 x 60 under max_constants=11 (the seed has 10): no individual ever has more than 11
    constants; the same search without the cap has individuals with more (so the cap did work)."""
    assert count_constants(Individual(parse(SEED))) == 10
    assert count_constants(Individual(parse("nVariance * pi + 2.0"))) == 2
    base = SearchParams(islands=2, population=60)
    capped = _population(SearchParams(**{**base.__dict__, "max_constants": 11}), seed=2)
    free = _population(base, seed=2)
    assert max(count_constants(t) for t in capped) <= 11
    assert max(count_constants(t) for t in free) > 11


def test_a_seed_over_the_constant_cap_is_refused():
    with pytest.raises(ValueError, match="seed has 10 constants, over max_constants=9"):
        _search(SearchParams(max_constants=9))


# -- colour variance ------------------------------------------------------------------------------------


def test_color_variance_is_read_from_color_var_unscaled():
    from src.models.filters.gp_filter import GPFilter

    flt = GPFilter("colorVariance * distance2(normal, normal)", 1, normalize=True)
    batch = {"color": torch.ones(1, 3, 4, 4), "normal": torch.ones(1, 3, 4, 4) * 2.0}
    batch["color_var"] = torch.arange(16.0).view(1, 1, 4, 4)
    assert torch.equal(flt.features(batch)["colorVariance"], batch["color_var"])
    del batch["color_var"]
    with pytest.raises(Exception, match="needs feature 'colorVariance': no batch key 'color_var'"):
        flt.features(batch)


# -- hall of fame and cache -----------------------------------------------------------------------------


def test_hall_of_fame_best_is_the_best_over_the_history_and_is_reported():
    """With hall_of_fame=5 each island's reported best (`best_per_island`) is the lowest best its island
    ever had in the history, and its hall holds 5 distinct expressions, best first; for some island that
    is lower than its last generation's best (little replication loses bests), which is what it fixes."""
    params = SearchParams(
        islands=3, population=12, generations=10, replication=0.0, crossover=0.5, mutation=0.5
    )
    params = SearchParams(**{**params.__dict__, "hall_of_fame": 5, "seed": 1})
    state = GPSearch(_TextFitness(), SEED, params, *_pset_book()).run()
    lost = 0
    for k, (best, hall) in enumerate(zip(best_per_island(state), state.halls, strict=True)):
        ever = min(h["islands"][k]["best"] for h in state.history)
        assert best.fitness.values[0] == ever == _text_fitness(str(best))
        values = [ind.fitness.values[0] for ind in hall]
        assert len(hall) == 5 and values == sorted(values) and len({str(i) for i in hall}) == 5
        lost += ever < state.history[-1]["islands"][k]["best"]
    assert lost > 0
    plain = GPSearch(
        _TextFitness(), SEED, SearchParams(**{**params.__dict__, "hall_of_fame": 0}), *_pset_book()
    )
    last = plain.run()
    assert last.halls is None and _texts(last) == _texts(state)  # the hall changes no population


def test_best_expressions_lists_each_islands_hall_of_fame_best_first():
    """best_expressions.yaml's rows (`best_expressions`): islands ordered by their best, each row's model
    the first of its hall, its `top` the whole hall in order (fitness and infix text); without a hall,
    `top` is the island's one best."""
    from src.gp.text import to_infix
    from src.tasks.filter_search import best_expressions
    from tests.conftest import compose_config

    cfg = compose_config(["task=filter_search", "task.search.radius=3"])
    params = SearchParams(islands=3, population=12, generations=4, hall_of_fame=4, seed=2)
    state = GPSearch(_TextFitness(), SEED, params, *_pset_book()).run()
    rows = best_expressions(state, cfg)
    assert [r["fitness"] for r in rows] == sorted(h[0].fitness.values[0] for h in state.halls)
    for row in rows:
        hall = state.halls[row["island"]]
        assert row["top"] == [{"fitness": i.fitness.values[0], "expression": to_infix(i)} for i in hall]
        assert row["model"] == {
            "name": "gp_filter",
            "expression": to_infix(hall[0]),
            "radius": 3,
            "normalize": True,
        }
    plain = GPSearch(
        _TextFitness(), SEED, SearchParams(**{**params.__dict__, "hall_of_fame": 0}), *_pset_book()
    )
    last = plain.run()
    for row in best_expressions(last, cfg):
        best = min(last.islands[row["island"]], key=lambda i: i.fitness.values[0])
        assert row["top"] == [{"fitness": best.fitness.values[0], "expression": to_infix(best)}]


def test_resume_with_a_hall_of_fame_gives_the_same_halls_and_populations(tmp_path):
    params = SearchParams(
        islands=2, population=8, generations=6, migration_interval=2, seed=3, hall_of_fame=4
    )
    whole = _search(params).run()
    ckpt = tmp_path / "state.json"
    _search(SearchParams(**{**params.__dict__, "generations": 3})).run(checkpoint=ckpt)
    random.seed(99)
    resumed = _search(params).run(state=load_state(ckpt, params), checkpoint=ckpt)
    assert _texts(resumed) == _texts(whole)
    assert [[(str(i), i.fitness.values) for i in h] for h in resumed.halls] == [
        [(str(i), i.fitness.values) for i in h] for h in whole.halls
    ]
    with pytest.raises(Exception, match="hall_of_fame"):
        load_state(ckpt, SearchParams(**{**params.__dict__, "hall_of_fame": 0}))


class _CountingFitness(Fitness):
    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.texts: list[str] = []

    def __call__(self, trees):
        self.texts += [str(t) for t in trees]
        return super().__call__(trees)


def test_fitness_cache_changes_no_result_and_skips_repeated_expressions():
    """The same seeded search on real images (relMSE fitness) with and without the cache: identical
    populations, fitness values and history; with the cache no expression is filtered twice, without it
    some are (replicas of lost individuals, unchanged crossover children), and the hits are counted."""
    feats, color, ref = _images()
    params = SearchParams(islands=2, population=10, generations=4, migration_interval=2, seed=6)
    runs = {}
    for cache in (True, False):
        fit = _CountingFitness(feats, color, ref, radius=2, tree_batch=5)
        search = GPSearch(
            fit, SEED, SearchParams(**{**params.__dict__, "fitness_cache": cache}), *_pset_book()
        )
        runs[cache] = (search.run(), fit.texts, search.cache_hits)
    (on, on_texts, hits), (off, off_texts, _) = runs[True], runs[False]
    assert _texts(on) == _texts(off) and on.history == off.history
    assert [[i.fitness.values for i in isl] for isl in on.islands] == [
        [i.fitness.values for i in isl] for isl in off.islands
    ]
    assert len(on_texts) == len(set(on_texts))
    assert len(off_texts) - len(on_texts) == hits > 0


def test_a_resumed_search_starts_with_its_checkpoint_in_the_cache(tmp_path):
    """The cache holds every island member and every hall-of-fame member of the checkpoint."""
    fit = _TextFitness()
    params = SearchParams(islands=2, population=6, generations=2, seed=3)
    _search(params).run(checkpoint=tmp_path / "s.json")
    state = load_state(tmp_path / "s.json", params)
    search = GPSearch(fit, SEED, params, *_pset_book())
    search.remember(state)
    members = [i for isl in state.islands for i in isl] + [i for hall in state.halls for i in hall]
    assert {str(i) for i in members} - {str(i) for isl in state.islands for i in isl}  # the halls add some
    assert set(search.cache) == {str(i) for i in members}
    assert all(search.cache[str(i)] == i.fitness.values[0] for i in members)


@pytest.mark.parametrize("rule, p_vector", [("thesis", 4 / 6), ("type_first", 1 / 2)])
def test_the_search_mates_by_its_crossover_rule(rule, p_vector):
    """`GPSearch`'s crossover follows `crossover_points`: on the two parents above, 2000 crossovers
    exchange a vector leaf (child 1 reads color) with probability 4/6 (thesis) or 1/2 (type-first).
    Mixed pairs, so that a leaf exchange leaves its sibling as it is."""
    params = SearchParams(crossover_points=rule, max_length=200, vector_pairs="mixed")
    search = GPSearch(_TextFitness(), SEED, params, *_pset_book())
    a = Individual(parse("neg(distance2(normal, depth))"))
    b = Individual(parse("distance1(color, color) + 2.0"))
    random.seed(8)
    n, leaf = 2000, 0
    for _ in range(n):
        child, _ = search.variation.mate(Individual(a), Individual(b))
        leaf += str(child) in ("neg(distance2(color, depth))", "neg(distance2(normal, color))")
    assert _within(leaf, n, p_vector), leaf / n


def test_a_checkpoint_resumes_with_the_cache_on_or_off(tmp_path):
    """`fitness_cache` changes no result, so a checkpoint resumes under either setting."""
    params = SearchParams(islands=2, population=6, generations=2, seed=3)
    _search(params).run(checkpoint=tmp_path / "s.json")
    off = SearchParams(**{**params.__dict__, "fitness_cache": False})
    assert load_state(tmp_path / "s.json", off).generation == 2


def test_asking_for_the_colour_variance_without_it_in_the_data_is_one_line():
    from src.errors import ConfigError
    from src.tasks.filter_search import make_search
    from tests.conftest import compose_config, one_line_error

    cfg = compose_config(["task=filter_search", "task.search.color_variance=true", "task.search.out_dir=x"])
    with pytest.raises(ConfigError) as excinfo:
        make_search(cfg, _TextFitness(), ["normal", "nVariance"])
    one_line_error(excinfo, "task.search.color_variance=true", "'color_var'", "stage=preprocess again")
    search, pset = make_search(cfg, _TextFitness(), ["normal", "colorVariance"])
    assert "colorVariance" in {t.name for t in pset.terminals[float]}
    assert search.params.color_variance is True


def test_a_checkpoint_from_before_the_options_resumes_under_their_defaults(tmp_path):
    """A state.json written before these options existed holds the rules of then (mixed pairs,
    type-first crossover, per-draw shares, no hall of fame, no colour variance): it loads for those, and
    is refused for today's defaults, the thesis's rules (naming them)."""
    import json

    from src.gp.search import PRE_OPTION_RULES

    params = SearchParams(islands=2, population=6, generations=2, seed=3, **PRE_OPTION_RULES)
    path = tmp_path / "s.json"
    _search(params).run(checkpoint=path)
    data = json.loads(path.read_text())
    new = (
        "vector_pairs",
        "crossover_points",
        "shares_count",
        "max_constants",
        "hall_of_fame",
        "color_variance",
    )
    data["params"] = {k: v for k, v in data["params"].items() if k not in new + ("fitness_cache",)}
    path.write_text(json.dumps(data))
    assert load_state(path, params).generation == 2
    with pytest.raises(Exception, match=r"other parameters \(vector_pairs\)"):
        load_state(path, SearchParams(**{**params.__dict__, "vector_pairs": "same"}))
    today = "color_variance, crossover_points, hall_of_fame, shares_count, vector_pairs"
    with pytest.raises(Exception, match=rf"other parameters \({today}\)"):
        load_state(path, SearchParams(islands=2, population=6, generations=2, seed=3))
