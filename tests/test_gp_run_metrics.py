"""The filter search's end-of-run metrics (src/gp/run_metrics.py) by value, on hand-made histories and
expressions."""

from __future__ import annotations

import pytest

from src.gp.run_metrics import COUNTED_FEATURES, RIVALS, best_through, feature_counts, search_run_metrics


def _history(bests_per_generation):
    return [
        {"generation": g, "evaluations": 1, "islands": [{"best": b, "mean": b, "invalid": 0} for b in bests]}
        for g, bests in enumerate(bests_per_generation)
    ]


# Generation 2 loses generation 1's best (0.3): the best so far must stay 0.3, not rise to 0.4.
HISTORY = _history([[0.5, 0.6], [0.7, 0.3], [0.4, 0.45], [0.35, 0.9], [0.2, 0.8], [0.25, 0.1]])
SEED = (
    "exp(-(distance2(pixel, pixel) ** 2.0 / 50.0 + distance2(color, color) ** 2.0 / 0.5"
    " + distance2(normal, normal) ** 2.0 / 0.18 + distance2(texture, texture) ** 2.0 / 0.02"
    " + distance2(depth, depth) ** 2.0 / 0.005))"
)


@pytest.mark.parametrize("generation, best", [(0, 0.5), (1, 0.3), (2, 0.3), (3, 0.3), (4, 0.2), (5, 0.1)])
def test_best_through_is_the_minimum_over_every_island_up_to_the_generation(generation, best):
    assert best_through(HISTORY, generation) == best


def test_best_through_before_the_first_record_is_an_error():
    with pytest.raises(ValueError, match="generation -1"):
        best_through(HISTORY, -1)


def test_feature_counts_count_nodes_and_leave_out_pixel_and_constants():
    counts = feature_counts(SEED)
    assert counts == {"color": 2, "normal": 2, "texture": 2, "depth": 2}
    mixed = feature_counts("exp(-(distance2(normal, normal) ** 2.0 * nVariance + dot(depth, worldPosition)))")
    assert mixed == {"normal": 2, "nVariance": 1, "depth": 1, "worldPosition": 1}


def test_search_run_metrics_by_value():
    expression = "exp(-(distance2(normal, normal) * distance1(normal, normal) + distance2(depth, depth)))"
    metrics = search_run_metrics(HISTORY, expression)
    assert metrics["search_best_initial"] == 0.5
    # last generation 5: midway is generation 2 (floor), where the best so far is 0.3 (not 0.2 of gen. 4)
    assert metrics["search_best_midway"] == 0.3
    assert metrics["search_feature_normal"] == 4.0 and metrics["search_feature_depth"] == 2.0
    assert metrics["search_feature_top_rival"] == 2.0  # depth: the most used feature but normal
    assert {k for k in metrics if k.startswith("search_feature_")} == {
        *(f"search_feature_{f}" for f in COUNTED_FEATURES),
        "search_feature_top_rival",
    }
    assert metrics["search_feature_color"] == 0.0 and metrics["search_feature_wpVariance"] == 0.0
    assert "search_feature_pixel" not in metrics


def test_midway_of_an_even_number_of_generations_is_its_half():
    metrics = search_run_metrics(HISTORY[:5], SEED)  # last generation 4: midway 2
    assert metrics["search_best_midway"] == 0.3
    metrics = search_run_metrics(_history([[0.5], [0.4], [0.3], [0.2], [0.1]]), SEED)
    assert metrics["search_best_midway"] == 0.3 and metrics["search_best_initial"] == 0.5


def test_the_rivals_of_normal_are_the_grammar_features_not_colour():
    assert "normal" not in RIVALS and "color" not in RIVALS and "pixel" not in RIVALS
    assert {"texture", "directIllumination", "depth", "worldPosition"} <= set(RIVALS)
    # the seed uses colour most with normal, texture and depth: colour does not count against normal
    metrics = search_run_metrics(HISTORY, "exp(-(distance2(color, color) * distance2(color, normal)))")
    assert metrics["search_feature_top_rival"] == 0.0 and metrics["search_feature_normal"] == 1.0
