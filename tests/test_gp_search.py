"""The GP search (src/gp/search.py, Davletaliyev 2016 Sec. 3.2) on tiny synthetic images, and
`task=filter_search` end to end (slow)."""

import json
import os
import random
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from src.gp.grammar import GRAMMAR_VECTORS
from src.gp.published import bilateral_expression
from src.gp.search import (
    WORST,
    Fitness,
    GPSearch,
    Individual,
    SearchParams,
    codebook,
    cx_one_point,
    kernel_expressions,
    load_state,
    mut_delete,
    mut_insert,
    mut_replace,
    mut_swap,
    save_state,
    search_pset,
)
from src.gp.text import parse
from tests.conftest import ROOT

AVAILABLE = ["color", "normal", "texture", "depth", "nGradient"]
SEED = bilateral_expression(5.0, 0.5, 0.3, 0.1, 0.05)


def _pset_book():
    pset = search_pset(AVAILABLE)
    return pset, codebook(kernel_expressions([f for f in GRAMMAR_VECTORS if f in AVAILABLE]), pset)


def _images(n=2, size=16, noise=0.3):
    g = torch.Generator().manual_seed(0)
    # piecewise-constant reference (two halves) so that feature-aware weights help
    ref = torch.full((n, 3, size, size), 0.2)
    ref[..., size // 2 :] = 0.8
    color = (ref + noise * torch.randn(n, 3, size, size, generator=g)).clamp(min=0)
    normal = torch.zeros(n, 3, size, size)
    normal[:, 2, :, : size // 2] = 1.0
    normal[:, 0, :, size // 2 :] = 1.0
    feats = {
        "color": color,
        "normal": normal,
        "texture": ref.clone(),
        "depth": ref[:, :1].clone(),
        "nGradient": torch.zeros(n, 3, size, size),
    }
    return feats, color, ref


def _search(params, fitness=None):
    pset, book = _pset_book()
    feats, color, ref = _images()
    return GPSearch(fitness or Fitness(feats, color, ref, radius=2), SEED, params, pset, book)


def _texts(state):
    return [[str(ind) for ind in island] for island in state.islands]


def test_seeded_island_holds_10_percent_copies_and_mutants():
    random.seed(3)
    search = _search(SearchParams(islands=1, population=20))
    island = search.seeded_island()
    assert len(island) == 20
    copies = sum(str(ind) == str(search.seed) for ind in island)
    assert 2 <= copies < 20  # 10% copies, the rest mutants (a mutation may give the seed back)
    assert all(str(ind) == str(search.seed) for ind in island[:2])


def _typed_ok(tree):
    """Every node's return type is what its parent's argument wants, and the root is a float."""
    tree = parse(str(tree))  # parse checks types
    return tree[0].ret is float


@pytest.mark.parametrize("kind", ["insert", "replace", "swap", "delete"])
def test_each_mutation_keeps_types_and_the_length_limit(kind):
    pset, book = _pset_book()
    search = _search(SearchParams(max_length=45, mutation_kinds={kind: 1.0}))
    random.seed(0)
    for _ in range(60):
        (child,) = search.variation.mutate(Individual(parse(SEED, pset)))
        assert _typed_ok(child)
        assert len(child) <= 45
    ind = Individual(parse(SEED, pset))
    op = {
        "insert": lambda t: mut_insert(t, book, pset),
        "replace": lambda t: mut_replace(t, pset),
        "swap": mut_swap,
        "delete": lambda t: mut_delete(t, pset),
    }[kind]
    changed = 0
    for _ in range(30):
        (out,) = op(Individual(parse(SEED, pset)))
        assert _typed_ok(out)
        changed += str(out) != str(ind)
    assert changed > 0


def test_delete_at_a_vector_replaces_its_vector_operator():
    pset, _ = _pset_book()
    random.seed(0)
    # exp(neg(distance2(normal, normal))): a point on exp, on neg, or on distance2 or one of its two vector
    # terminals (which deletes distance2's whole subtree): 1/5, 1/5, 3/5.
    expected = {"1.0": 1 / 5, "exp(1.0)": 1 / 5, "exp(neg(1.0))": 3 / 5}
    seen = {text: 0 for text in expected}
    draws = 300
    for _ in range(draws):
        (out,) = mut_delete(Individual(parse("exp(-distance2(normal, normal))", pset)), pset)
        assert str(out) in expected and _typed_ok(out)
        seen[str(out)] += 1
    for text, p in expected.items():
        assert abs(seen[text] - draws * p) <= 4 * (draws * p * (1 - p)) ** 0.5, seen


def test_crossover_exchanges_only_subtrees_of_one_type():
    pset, _ = _pset_book()
    random.seed(1)
    a_text, b_text = SEED, "mitchell(distance1(depth, texture)) * 0.3"
    for _ in range(50):
        a, b = cx_one_point(Individual(parse(a_text, pset)), Individual(parse(b_text, pset)))
        assert _typed_ok(a) and _typed_ok(b)
        assert len(a) + len(b) == len(parse(a_text)) + len(parse(b_text))


def test_migration_moves_each_islands_best_to_the_next_island():
    search = _search(SearchParams(islands=3, population=4))
    islands = []
    for k in range(3):
        island = []
        for j in range(4):
            ind = Individual(parse(f"{float(10 * k + j + 1)!r} * 1.0"))
            ind.fitness.values = (float(10 * k + j + 1),)
            island.append(ind)
        islands.append(island)
    before = [list(island) for island in islands]
    search.migrate(islands)
    for k in range(3):
        # the previous island's best (fitness 10 (k - 1) + 1) took the place of this island's worst (last)
        best_before = float(10 * ((k - 1) % 3) + 1)
        values = [ind.fitness.values[0] for ind in islands[k]]
        assert values == [10 * k + 1, 10 * k + 2, 10 * k + 3, best_before]
        assert str(islands[k][3]) == str(before[(k - 1) % 3][0])
        assert all(a is b for a, b in zip(islands[k][:3], before[k][:3], strict=True))  # the rest stayed
    assert len({id(ind) for island in islands for ind in island}) == 12  # copies, not shared objects


def test_fitness_orders_identity_below_bilateral_and_undefined_is_worst():
    feats, color, ref = _images()
    fitness = Fitness(feats, color, ref, radius=2)
    identity = parse("biweight(distance1(pixel, pixel))")  # weight only at q = p: the noisy image
    bilateral = parse(SEED)
    undefined = parse("sqrt(neg(2.0))")
    values = fitness([identity, bilateral, undefined])
    assert values[0] == pytest.approx(1.0, abs=1e-5)  # filtered == noisy
    assert values[1] < 0.8  # the bilateral seed removes noise on the two flat halves
    assert values[2] == WORST == sys.float_info.max


def test_fitness_is_the_ratio_of_eq_3_5():
    import numpy as np

    from src.metrics.image import relmse_spp

    feats, color, ref = _images(n=1)
    tree = parse(SEED)
    value = Fitness(feats, color, ref, radius=2)([tree])[0]
    from src.gp.evaluate import filter_images

    out = filter_images([tree], feats, color, 2).color[0]
    hwc = [np.asarray(x[0].permute(1, 2, 0)) for x in (out, color, ref)]
    expected = relmse_spp(hwc[0], hwc[2], 8) / relmse_spp(hwc[1], hwc[2], 8)
    assert value == pytest.approx(expected, rel=1e-4)


def test_a_search_is_deterministic_under_its_seed():
    params = SearchParams(islands=2, population=6, generations=3, migration_interval=2, seed=7)
    a = _search(params).run()
    random.seed(12345)  # whatever the global state before
    b = _search(params).run()
    assert _texts(a) == _texts(b)
    assert a.history == b.history
    c = _search(SearchParams(islands=2, population=6, generations=3, migration_interval=2, seed=8)).run()
    assert _texts(c) != _texts(a)


def test_resume_from_a_checkpoint_gives_the_same_final_populations(tmp_path):
    params = SearchParams(islands=2, population=6, generations=4, migration_interval=2, seed=3)
    whole = _search(params).run()
    ckpt = tmp_path / "search.json"
    short = SearchParams(**{**params.__dict__, "generations": 2})
    _search(short).run(checkpoint=ckpt)
    random.seed(999)  # a fresh process: the global RNG is anywhere
    state = load_state(ckpt, params)
    assert state.generation == 2
    resumed = _search(params).run(state=state, checkpoint=ckpt)
    assert _texts(resumed) == _texts(whole)
    assert [[i.fitness.values for i in isl] for isl in resumed.islands] == [
        [i.fitness.values for i in isl] for isl in whole.islands
    ]
    save_state(tmp_path / "again.json", resumed, params)
    other = SearchParams(**{**params.__dict__, "tournament_size": 3})
    with pytest.raises(Exception, match="tournament_size"):
        load_state(ckpt, other)


def _resume_and_dump(checkpoint: str, out: str) -> None:
    """Run in a fresh interpreter by the test below: resume `checkpoint` to 4 generations, dump the texts."""
    params = SearchParams(islands=2, population=6, generations=4, migration_interval=2, seed=3)
    resumed = _search(params).run(state=load_state(checkpoint, params))
    Path(out).write_text(json.dumps(_texts(resumed)))


def test_resume_in_another_process_gives_the_same_final_populations(tmp_path):
    """A resume in a new interpreter (its own RNG state, hash seed and object ids, on which DEAP's sets of
    primitive types depend) gives the uninterrupted run's populations."""
    params = SearchParams(islands=2, population=6, generations=4, migration_interval=2, seed=3)
    whole = _search(params).run()
    ckpt, out = tmp_path / "search.json", tmp_path / "resumed.json"
    _search(SearchParams(**{**params.__dict__, "generations": 2})).run(checkpoint=ckpt)
    code = f"from tests.test_gp_search import _resume_and_dump; _resume_and_dump({str(ckpt)!r}, {str(out)!r})"
    env = {**os.environ, "PYTHONHASHSEED": "12345"}
    subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, check=True, timeout=300)
    assert json.loads(out.read_text()) == _texts(whole)


def test_an_operator_with_two_equal_arguments_evaluates():
    """Regression (found by the search): mul(x, x) of a varying x freed x twice (KeyError)."""
    from src.gp.evaluate import filter_images

    feats, color, _ = _images(n=1)
    tree = parse("exp(-(distance2(depth, depth) ** 2.0 * distance2(depth, depth) ** 2.0))")
    assert bool(filter_images([tree], feats, color, 1).valid[0].all())


def test_search_images_follow_spp_then_max_images():
    from src.tasks.filter_search import search_image_indices

    images = [{"scene": s, "spp": n} for s in ("a", "b") for n in (4, 16)]
    assert search_image_indices(images, [4], None) == [0, 2]
    assert search_image_indices(images, None, 3) == [0, 1, 2]
    assert search_image_indices(images, [16], 1) == [1]
    assert search_image_indices(images, [8], None) == []


def test_searching_on_an_unrendered_spp_fails_at_job_start():
    from omegaconf import OmegaConf

    from src.errors import ConfigError
    from src.tasks.filter_search import FilterSearchTask
    from tests.conftest import compose_config, one_line_error

    cfg = compose_config(["task=filter_search", "profile=smoke", "task.search.spp=[4,8]"])
    with pytest.raises(ConfigError) as excinfo:
        FilterSearchTask().check_stages(["render", "search"], cfg)
    one_line_error(excinfo, "task.search.spp=[4, 8]", "[8] not rendered", "dataset.noisy_spp=[4, 16]")
    OmegaConf.update(cfg, "task.search.spp", [4])
    FilterSearchTask().check_stages(["render", "search"], cfg)


@pytest.mark.slow
def test_filter_search_task_end_to_end(smoke_data, tmp_path):
    """render + preprocess (the denoise task's, up to date from the fixture), search 2 islands x 4 for 2
    generations, eval of the best expression as gp_filter; then a resumed search continues its state."""
    import json

    import yaml

    from src import stages
    from src.schema.run import validate_run
    from src.tracking.tracker import Tracker
    from tests.conftest import smoke_config

    overrides = ["task=filter_search", "task.search.islands=2", "task.search.population=4"]
    cfg = smoke_config(smoke_data, tmp_path / "run", [*overrides, "task.search.generations=2"])
    validate_run(cfg)
    stages.render(cfg)
    stages.preprocess(cfg)
    summary = stages.search(cfg, Tracker(None))
    out = tmp_path / "run" / "search"
    rows = yaml.safe_load((out / "best_expressions.yaml").read_text())
    assert len(rows) == 2 and rows[0]["fitness"] <= rows[1]["fitness"]
    assert rows[0]["model"]["expression"] == summary["best_expression"]
    assert summary["best_fitness"] < 1.0  # the filter beats the noisy input
    assert summary["images"] and {m["spp"] for m in summary["images"]} == {4}  # task.search.spp
    history = json.loads((out / "history.json").read_text())
    assert [h["generation"] for h in history] == [0, 1, 2]
    assert [len(h["islands"]) for h in history] == [2, 2, 2]
    result = stages.evaluate(cfg, Tracker(None))
    metrics = json.loads((tmp_path / "run" / "eval" / "metrics.json").read_text())
    assert metrics["model"] == "gp_filter" and result["mean"]["relmse"] < result["mean"]["noisy_relmse"]
    import pandas as pd

    islands = pd.read_csv(tmp_path / "run" / "eval" / "islands.csv")  # every island's best, held out
    assert list(islands["island"]) == [r["island"] for r in rows]
    assert islands["psnr"].iloc[0] == pytest.approx(result["mean"]["psnr"])
    assert list(islands["expression"]) == [r["model"]["expression"] for r in rows]
    assert (tmp_path / "run" / "eval" / f"island{rows[1]['island']}" / "metrics.json").exists()
    # resume: two more generations from the checkpoint
    more = smoke_config(
        smoke_data,
        tmp_path / "run2",
        [*overrides, "task.search.generations=4", f"task.search.resume={out / 'state.json'}"],
    )
    assert stages.search(more, Tracker(None))["generations"] == 4
