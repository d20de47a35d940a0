"""The GP search (src/gp/search.py, its operators src/gp/variation.py and fitness src/gp/fitness.py;
Davletaliyev 2016 Sec. 3.2) on tiny synthetic images, and `task=filter_search` end to end."""

import json
import os
import random
import re
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
import torch

from src.errors import ConfigError, DataError
from src.gp.fitness import WORST, Fitness, relative_error
from src.gp.grammar import GRAMMAR_VECTORS, Vector
from src.gp.published import bilateral_expression
from src.gp.search import GPSearch, Individual, SearchParams, load_state, save_state, search_pset
from src.gp.text import parse
from src.gp.variation import (
    codebook,
    cx_one_point,
    kernel_expressions,
    mut_delete,
    mut_insert,
    mut_replace,
    mut_swap,
)
from src.metrics.image import relmse_spp
from tests.conftest import ROOT, compose_config, one_line_error

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


def test_a_child_over_max_length_is_replaced_by_its_parent(monkeypatch):
    """`Variation` (as `GPSearch` builds it from `SearchParams`): a mutation or crossover child of exactly
    `max_length` nodes is kept, one node more and its parent comes back (`gp.staticLimit`)."""
    import src.gp.variation as variation_module

    pset, book = _pset_book()
    parent = Individual(parse(SEED, pset))
    grown = Individual(parse(f"({SEED}) * 2.0", pset))
    monkeypatch.setattr(variation_module, "mut_insert", lambda ind, *args, **kw: (Individual(grown),))
    for rule in ("cx_one_point", "cx_thesis"):
        monkeypatch.setattr(variation_module, rule, lambda a, b, **kw: (Individual(grown), Individual(grown)))
    for limit, kept in ((len(grown), True), (len(grown) - 1, False)):
        params = SearchParams(max_length=limit, mutation_kinds={"insert": 1.0})
        search = GPSearch(_TextFitness(), SEED, params, pset, book)
        want = str(grown) if kept else str(parent)
        (child,) = search.variation.mutate(Individual(parent))
        assert str(child) == want
        assert [str(c) for c in search.variation.mate(Individual(parent), Individual(parent))] == [want, want]


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


def test_searching_on_an_unrendered_spp_fails_at_job_start(tmp_path):
    from omegaconf import OmegaConf

    from src.errors import ConfigError
    from src.tasks.filter_search import FilterSearchTask
    from tests.conftest import compose_config, one_line_error

    # paths.data: the job-start checks look for the prepared folder (none here)
    cfg = compose_config(
        ["task=filter_search", "profile=smoke", "task.search.spp=[4,8]", f"paths.data={tmp_path}"]
    )
    with pytest.raises(ConfigError) as excinfo:
        FilterSearchTask.for_run(cfg).check_stages(["render", "search"], cfg)
    one_line_error(excinfo, "task.search.spp=[4, 8]", "[8] not rendered", "dataset.noisy_spp=[4, 16]")
    OmegaConf.update(cfg, "task.search.spp", [4])
    FilterSearchTask.for_run(cfg).check_stages(["render", "search"], cfg)


def test_filter_search_task_end_to_end(smoke_data, tmp_path, monkeypatch):
    """render + preprocess (on a copy of the fixture's data: this task's smoke split differs), search 2
    islands x 4 for 2 generations, eval of the best expression as gp_filter; a search interrupted for a
    requeue continues its own state in its folder to the same result; a resumed search continues its
    state."""
    import json
    import shutil

    import yaml

    from src import stages
    from src.schema.run import validate_run
    from src.tracking.tracker import Tracker
    from tests.conftest import smoke_config

    # Its own copy of the shared smoke data: task=filter_search renders two scenes per base at this profile
    # and splits them by base (conf/task/filter_search.yaml), which must not change the shared folder.
    data = tmp_path / "data"
    shutil.copytree(smoke_data, data)
    overrides = ["task=filter_search", "task.search.islands=2", "task.search.population=4"]
    cfg = smoke_config(data, tmp_path / "run", [*overrides, "task.search.generations=2"])
    validate_run(cfg)
    stages.render(cfg)
    stages.preprocess(cfg)

    class Recorder(Tracker):
        def __init__(self):
            super().__init__(None)
            self.logged: dict[str, float] = {}

        def log_metrics(self, metrics, step=None):
            self.logged |= dict(metrics)

    recorder = Recorder()
    summary = stages.search(cfg, recorder)
    out = tmp_path / "run" / "search"
    rows = yaml.safe_load((out / "best_expressions.yaml").read_text())
    assert len(rows) == 2 and rows[0]["fitness"] <= rows[1]["fitness"]
    assert rows[0]["model"]["expression"] == summary["best_expression"]
    assert summary["best_fitness"] < 1.0  # the filter beats the noisy input
    assert summary["images"] and {m["spp"] for m in summary["images"]} == {4}  # task.search.spp
    history = json.loads((out / "history.json").read_text())
    assert [h["generation"] for h in history] == [0, 1, 2]
    assert [len(h["islands"]) for h in history] == [2, 2, 2]
    # the end-of-search metrics, from history.json and the best expression's text (src/gp/run_metrics.py)
    logged = recorder.logged
    assert logged["search_best_initial"] == min(i["best"] for i in history[0]["islands"])
    assert logged["search_best_midway"] == min(i["best"] for h in history[:2] for i in h["islands"])
    assert logged["search_best_so_far"] == min(i["best"] for h in history for i in h["islands"])
    for feature in ("normal", "depth", "color", "texture"):
        assert logged[f"search_feature_{feature}"] == len(
            re.findall(rf"\b{feature}\b", summary["best_expression"])
        )
    result = stages.evaluate(cfg, Tracker(None))
    metrics = json.loads((tmp_path / "run" / "eval" / "metrics.json").read_text())
    assert metrics["model"] == "gp_filter" and result["mean"]["relmse"] < result["mean"]["noisy_relmse"]
    import pandas as pd

    islands = pd.read_csv(tmp_path / "run" / "eval" / "islands.csv")  # every island's best, held out
    assert list(islands["island"]) == [str(r["island"]) for r in rows] + ["baseline"]
    assert islands["psnr"].iloc[0] == pytest.approx(result["mean"]["psnr"])
    assert list(islands["expression"]) == [r["model"]["expression"] for r in rows] + ["cross_bilateral"]
    # the constant-sigma cross-bilateral filter, scored once, on the same held-out images
    assert islands["psnr"].iloc[-1] == pytest.approx(result["mean"]["baseline_psnr"])
    per_image = pd.read_csv(tmp_path / "run" / "eval" / "per_image.csv")
    assert per_image["baseline_relmse_spp"].notna().all() and per_image["relmse_spp"].notna().all()
    island_rows = pd.read_csv(tmp_path / "run" / "eval" / f"island{rows[1]['island']}" / "per_image.csv")
    assert not [c for c in island_rows if c.startswith("baseline_")]
    assert (tmp_path / "run" / "eval" / f"island{rows[1]['island']}" / "metrics.json").exists()
    # A job starting again in its run folder (a requeue) continues its own state, not another config's.
    from src.gp.search import GPSearch, saved_job
    from src.provenance import config_digest
    from src.tasks.filter_search import resumable_search_state

    job = saved_job(out / "state.json")
    assert {k: job[k] for k in ("config_digest", "mlflow_run_id")} == {
        "config_digest": config_digest(cfg),
        "mlflow_run_id": None,
    }
    assert job["search_time_s"] > 0  # the search's clock at its last generation
    assert resumable_search_state(cfg) == out / "state.json"
    longer = smoke_config(data, tmp_path / "run", [*overrides, "task.search.generations=4"])
    assert resumable_search_state(longer) is None
    off = smoke_config(data, tmp_path / "run", [*overrides, "task.search.generations=2", "auto_resume=false"])
    assert resumable_search_state(off) is None
    requeued = smoke_config(data, tmp_path / "requeued", [*overrides, "task.search.generations=2"])
    step = GPSearch.step

    def exit_in_generation_2(self, state):
        if state.generation == 1:
            raise SystemExit(-1)  # submitit's exit after requeueing the job
        return step(self, state)

    monkeypatch.setattr(GPSearch, "step", exit_in_generation_2)
    with pytest.raises(SystemExit):
        stages.search(requeued, Tracker(None))
    assert json.loads((tmp_path / "requeued" / "search" / "state.json").read_text())["generation"] == 1
    monkeypatch.undo()
    interrupted_clock = saved_job(tmp_path / "requeued" / "search" / "state.json")["search_time_s"]
    again = stages.search(requeued, Tracker(None))  # no resume given: its own state.json, generation 1
    # the clock continues the interrupted job's: generation 2 ends after the time generations 0-1 took
    final_clock = saved_job(tmp_path / "requeued" / "search" / "state.json")["search_time_s"]
    assert interrupted_clock > 0 and final_clock > interrupted_clock
    assert again["best_expression"] == summary["best_expression"] and again["generations"] == 2
    assert json.loads((tmp_path / "requeued" / "search" / "history.json").read_text()) == history
    # resume: two more generations from the checkpoint
    more = smoke_config(
        smoke_data,
        tmp_path / "run2",
        [*overrides, "task.search.generations=4", f"task.search.resume={out / 'state.json'}"],
    )
    assert stages.search(more, Tracker(None))["generations"] == 4


# ---------------------------------------------------------------------------------------------------------
# Operators, migration and fitness observed by value (issue 30): a stand-in fitness of the text keeps these
# tests free of image filtering; the fitness itself is checked on images of unequal noise below.


def _text_fitness(text: str) -> float:
    """A deterministic stand-in fitness of an expression's text, in [0, 1): distinct texts get distinct
    values (crc32), so a fitness left over from another expression shows."""
    return zlib.crc32(text.encode()) / 2**32


class _TextFitness:
    """`_text_fitness` of each tree, recording the texts of every call."""

    def __init__(self):
        self.calls: list[list[str]] = []

    def __call__(self, trees):
        texts = [str(tree) for tree in trees]
        self.calls.append(texts)
        return [_text_fitness(text) for text in texts]


def _ranked_island(n):
    """n small distinct individuals with the fitness values 1, 2, ..., n (rank = value), shuffled."""
    island = []
    for j in range(n):
        ind = Individual(parse(f"{float(j + 1)!r} * 1.0"))
        ind.fitness.values = (float(j + 1),)
        island.append(ind)
    random.Random(n).shuffle(island)
    return island


def _within(count, n, p, sigmas=4.0):
    """count is within `sigmas` binomial standard deviations of n * p."""
    return abs(count - n * p) <= sigmas * (n * p * (1 - p)) ** 0.5


def test_offspring_operator_mix_under_the_per_draw_rule(monkeypatch):
    """`GPSearch.offspring` with `shares_count: draws` (the ablation; the thesis's per-individual rule is
    tested in test_gp_thesis_rules.py): per draw of
    r = random.random(), r < replication (0.10) adds one replica (a tournament winner, unchanged, fitness
    kept), r < replication + crossover (0.55) one crossover adding BOTH its children, each then mutated with
    probability crossover_mutation (0.85), else one mutant of a winner; the shares are per draw, not per
    individual (a crossover adds two), draws stop once the island is full, and a second crossover child
    beyond its size is cut. Every call to select / mate / mutate is logged; ~1400 draws over 40 islands."""
    params = SearchParams(islands=1, population=50, shares_count="draws")
    search = GPSearch(_TextFitness(), SEED, params, *_pset_book())
    events: list[str] = []
    select = search.select

    def logged_select(island):
        events.append("select")
        return select(island)

    def mate(a, b):
        events.append("mate")
        a.origin = b.origin = "crossover"
        return a, b

    def mutate(ind):
        events.append("cx-mutate" if getattr(ind, "origin", None) == "crossover" else "mutate")
        ind.origin = getattr(ind, "origin", None) or "mutation"
        return (ind,)

    monkeypatch.setattr(search, "select", logged_select)
    monkeypatch.setattr(search.variation, "mate", mate)
    monkeypatch.setattr(search.variation, "mutate", mutate)
    random.seed(11)
    island = _ranked_island(50)
    by_text = {str(ind): ind for ind in island}
    draws = {"replication": 0, "crossover": 0, "mutation": 0}
    cx_children = cx_mutations = 0
    for _ in range(40):
        events.clear()
        new = search.offspring(island)
        # parse the log into draws: select (replica) | select mutate | select select mate [cx-mutate]*
        kinds, i = [], 0
        while i < len(events):
            assert events[i] == "select", events
            if events[i + 1 : i + 3] == ["select", "mate"]:
                kinds.append("crossover")
                i += 3
                while i < len(events) and events[i] == "cx-mutate":
                    cx_mutations += 1
                    i += 1
            elif events[i + 1 : i + 2] == ["mutate"]:
                kinds.append("mutation")
                i += 2
            else:
                kinds.append("replication")
                i += 1
        sizes = [2 if kind == "crossover" else 1 for kind in kinds]
        assert sum(sizes[:-1]) < 50 <= sum(sizes) and len(new) == 50  # no draw once the island is full
        for kind in kinds:
            draws[kind] += 1
        cx_children += 2 * kinds.count("crossover")
        origins = [getattr(ind, "origin", None) for ind in new]
        assert origins.count(None) == kinds.count("replication")
        assert origins.count("mutation") == kinds.count("mutation")
        assert origins.count("crossover") == 2 * kinds.count("crossover") - (sum(sizes) - 50)
        for ind in new:
            if getattr(ind, "origin", None) is None:  # a replica: a copy of an island member, fitness kept
                parent = by_text[str(ind)]
                assert ind is not parent and ind.fitness.valid and ind.fitness.values == parent.fitness.values
            else:  # every varied child is evaluated again, whether or not its expression changed
                assert not ind.fitness.valid
    total = sum(draws.values())
    assert 40 * 50 / 1.45 * 0.95 < total < 40 * 50 / 1.45 * 1.05  # E[individuals per draw] = 1.45
    for kind, p in (("replication", 0.10), ("crossover", 0.45), ("mutation", 0.45)):
        assert _within(draws[kind], total, p), draws
    assert _within(cx_mutations, cx_children, 0.85)


def test_tournament_of_8_picks_the_lowest_fitness_of_its_draws():
    """`select`: the lowest fitness of 8 draws with replacement (`tools.selTournament`, tournament_size 8):
    P(rank <= j) = 1 - (1 - j / n)^8 over n ranked individuals; 3000 tournaments on 40 individuals."""
    search = GPSearch(_TextFitness(), SEED, SearchParams(), *_pset_book())
    island, n, k, draws = _ranked_island(40), 40, 8, 3000
    random.seed(5)
    ranks = []
    for _ in range(draws):
        winner = search.select(island)
        assert all(winner is not ind for ind in island)  # a copy
        ranks.append(int(winner.fitness.values[0]))
    p_rank = [((n - j + 1) / n) ** k - ((n - j) / n) ** k for j in range(1, n + 1)]  # P(rank = j)
    mean = sum(j * p for j, p in enumerate(p_rank, 1))
    sd = (sum(j * j * p for j, p in enumerate(p_rank, 1)) - mean**2) ** 0.5
    assert abs(sum(ranks) / draws - mean) < 4 * sd / draws**0.5
    for j in (1, 3, 8):
        assert _within(sum(r <= j for r in ranks), draws, 1 - (1 - j / n) ** k)


@pytest.mark.parametrize(
    "kinds",
    [
        {"insert": 0.3, "replace": 0.3, "swap": 0.3, "delete": 0.1},  # the default (the thesis's)
        {"insert": 1.0, "swap": 0.0, "delete": 3.0},  # a zero weight and an absent kind: never drawn
    ],
)
def test_mutation_kinds_are_drawn_with_their_weights(monkeypatch, kinds):
    """`Variation.mutate` draws one kind per call with `random.choices` weighted by `mutation_kinds` (the
    CURRENT rule), and runs that kind's operator; 3000 draws."""
    import src.gp.variation as variation_module

    counts = dict.fromkeys(("insert", "replace", "swap", "delete"), 0)

    def operator(kind):
        def run(individual, *args, **kwargs):
            counts[kind] += 1
            return (individual,)

        return run

    for kind in counts:
        monkeypatch.setattr(variation_module, f"mut_{kind}", operator(kind))
    search = GPSearch(_TextFitness(), SEED, SearchParams(mutation_kinds=kinds), *_pset_book())
    random.seed(2)
    ind, draws = Individual(parse("1.0 * 2.0")), 3000
    for _ in range(draws):
        (out,) = search.variation.mutate(ind)
        assert str(out) == "mul(1.0, 2.0)"
    total = sum(kinds.values())
    assert sum(counts.values()) == draws
    for kind, count in counts.items():
        p = kinds.get(kind, 0.0) / total
        assert count == 0 if p == 0 else _within(count, draws, p), counts


def test_seeded_island_is_the_seed_copies_then_one_mutation_each(monkeypatch):
    """`seeded_island`: max(1, round(0.1 n)) copies of the seed first, then n - copies calls of `mutate`,
    each on a fresh copy of the seed."""
    search = GPSearch(_TextFitness(), SEED, SearchParams(), *_pset_book())
    calls = []

    def mutate(ind):
        calls.append(str(ind))
        child = Individual(parse(f"{float(len(calls))!r}"))
        return (child,)

    monkeypatch.setattr(search.variation, "mutate", mutate)
    for n, copies in ((20, 2), (5, 1), (30, 3)):
        calls.clear()
        search.params = SearchParams(population=n)
        island = search.seeded_island()
        assert [str(ind) for ind in island[:copies]] == [str(search.seed)] * copies
        assert all(ind is not search.seed for ind in island)
        assert calls == [str(search.seed)] * (n - copies)
        assert [str(ind) for ind in island[copies:]] == [repr(float(j)) for j in range(1, n - copies + 1)]


def test_evaluate_gives_every_unevaluated_tree_its_fitness_once():
    fit = _TextFitness()
    search = GPSearch(fit, SEED, SearchParams(), *_pset_book())
    a, b, c, d = (Individual(parse(x)) for x in ("1.0 * 2.0", "1.0 * 2.0", "3.0", "5.0"))
    d.fitness.values = (7.0,)  # already evaluated: kept, not asked again
    search.evaluate([a, b, c, d])
    assert fit.calls == [["mul(1.0, 2.0)", "3.0"]]
    assert [x.fitness.values[0] for x in (a, b, c, d)] == [_text_fitness("mul(1.0, 2.0)")] * 2 + [
        _text_fitness("3.0"),
        7.0,
    ]
    search.evaluate([a, d])
    assert len(fit.calls) == 1  # nothing left to evaluate: no call


def test_fitness_is_recomputed_after_variation():
    """A child whose expression changed never keeps its parent's fitness: after every generation each
    individual's fitness is the fitness of its own text; the only trees evaluated are the varied children
    (distinct texts once each) that the fitness cache has not seen, replicas keep theirs; `evaluations`
    in the history counts every distinct varied text, cached or not."""
    fit = _TextFitness()
    search = GPSearch(fit, SEED, SearchParams(islands=2, population=12, seed=5), *_pset_book())
    fresh: list[list[str]] = []
    offspring = search.offspring

    def recording_offspring(island):
        out = offspring(island)
        fresh.append([str(ind) for ind in out if not ind.fitness.valid])
        return out

    search.offspring = recording_offspring
    state = search.start()
    changed = 0
    for generation in range(1, 5):
        fresh.clear()
        parents = {str(ind) for island in state.islands for ind in island}
        calls = len(fit.calls)
        state = search.step(state)
        for island in state.islands:
            for ind in island:
                assert ind.fitness.values == (_text_fitness(str(ind)),), str(ind)
                changed += str(ind) not in parents
        texts = list(dict.fromkeys(t for island in fresh for t in island))
        seen = {t for call in fit.calls[:calls] for t in call}
        new = [t for t in texts if t not in seen]
        assert fit.calls[calls:] == ([new] if new else [])
        assert state.history[-1]["generation"] == generation and state.history[-1]["evaluations"] == len(
            texts
        )
    assert changed > 20  # the variation did change expressions


def test_migration_is_on_schedule_and_moves_each_best_to_the_next_islands_worst():
    """Migration after generations 3 and 6 of 7 (migration_interval 3), never otherwise: a copy of island
    i's best takes the place of island (i + 1) mod 3's worst (the first of equal worst), computed here from
    the islands before migration."""
    fit = _TextFitness()
    search = GPSearch(
        fit, SEED, SearchParams(islands=3, population=6, migration_interval=3, seed=2), *_pset_book()
    )
    migrations = []
    migrate = search.migrate

    def recording_migrate(islands):
        before = [[(str(ind), ind.fitness.values[0]) for ind in island] for island in islands]
        migrate(islands)
        migrations.append(
            (before, [[(str(ind), ind.fitness.values[0]) for ind in island] for island in islands])
        )

    search.migrate = recording_migrate
    state = search.start()
    assert migrations == []
    for generation in range(1, 8):
        n = len(migrations)
        state = search.step(state)
        assert len(migrations) - n == (1 if generation in (3, 6) else 0), generation
        if generation not in (3, 6):
            continue
        before, after = migrations[-1]
        expected = [list(island) for island in before]
        for i in range(3):
            source, target = before[(i - 1) % 3], before[i]
            best = min(range(len(source)), key=lambda j: source[j][1])
            worst = max(range(len(target)), key=lambda j: target[j][1])
            assert source[best][1] < target[worst][1]  # a real exchange
            expected[i][worst] = source[best]
        assert after == expected
        assert [[(str(ind), ind.fitness.values[0]) for ind in island] for island in state.islands] == after


def test_migration_of_two_replaces_the_two_worst_in_place_and_two_islands_exchange():
    """migrants=2: island i's best and second best replace island (i + 1)'s worst and second worst, at their
    positions; with two islands each sends to the other."""
    search = GPSearch(_TextFitness(), SEED, SearchParams(islands=2, migrants=2), *_pset_book())
    islands = [_ranked_island(6), _ranked_island(6)]
    for ind in islands[1]:
        ind.fitness.values = (ind.fitness.values[0] + 0.5,)
    before = [[(str(ind), ind.fitness.values[0]) for ind in island] for island in islands]
    search.migrate(islands)
    for i in range(2):
        source, target = before[1 - i], before[i]
        expected = list(target)
        order = sorted(range(6), key=lambda j: source[j][1])
        worst = sorted(range(6), key=lambda j: -target[j][1])
        expected[worst[0]], expected[worst[1]] = source[order[0]], source[order[1]]
        assert [(str(ind), ind.fitness.values[0]) for ind in islands[i]] == expected


def _relmse_np(x, y, eps=0.01):
    """Per image: mean over pixels of the sum over channels of (x - y)^2 / (y^2 + eps) (Eq. 3.5 without
    its m/2 factor), numpy."""
    return ((x - y) ** 2 / (y**2 + eps)).sum(axis=1).reshape(len(x), -1).mean(axis=1)


def _box_np(x, r):
    """Box filter of radius r with replicate borders, numpy: what the constant weight computes."""
    _, _, h, w = x.shape
    p = np.pad(x, ((0, 0), (0, 0), (r, r), (r, r)), mode="edge")
    shifts = [
        p[:, :, r + dy : r + dy + h, r + dx : r + dx + w]
        for dy in range(-r, r + 1)
        for dx in range(-r, r + 1)
    ]
    return sum(shifts) / len(shifts)


def _unequal_noise_images():
    """Two 12x12 images of vertical stripes (0.2 / 0.8, per channel scaled), noise sigma 0.02 on the first
    and 0.5 on the second (negative colours included): a box filter worsens the first (it blurs the
    stripes more than there is noise) and improves the second, so the mean of the per-image ratios and the
    ratio of the means differ clearly."""
    g = torch.Generator().manual_seed(4)
    cols = torch.arange(12, dtype=torch.float64)
    stripes = torch.where((cols // 3) % 2 == 0, 0.2, 0.8).view(1, 1, 1, 12).expand(2, 3, 12, 12)
    ref = stripes * torch.tensor([1.0, 0.7, 1.3], dtype=torch.float64).view(1, 3, 1, 1)
    sigma = torch.tensor([0.02, 0.5], dtype=torch.float64).view(2, 1, 1, 1)
    color = ref + sigma * torch.randn(2, 3, 12, 12, generator=g, dtype=torch.float64)
    depth = torch.rand(2, 1, 12, 12, generator=g, dtype=torch.float64)
    depth[0] = 0.5  # constant on the first image: distance2(depth, depth) has a zero weight sum there
    return {"color": color, "depth": depth}, color, ref.contiguous()


def test_fitness_is_the_mean_of_per_image_ratios_on_images_of_unequal_noise():
    feats, color, ref = _unequal_noise_images()
    c, y = color.numpy(), ref.numpy()
    box = _box_np(c, 1)
    ratios = _relmse_np(box, y) / _relmse_np(c, y)
    expected = float(ratios.mean())
    ratio_of_means = float(_relmse_np(box, y).mean() / _relmse_np(c, y).mean())
    assert ratios[0] > 1.5 and ratios[1] < 0.5 and abs(expected - ratio_of_means) > 0.5  # the fixture bites
    trees = [
        parse("2.0"),  # the box filter
        parse("biweight(distance1(pixel, pixel))"),  # weight only at q = p: the noisy image, ratio 1
        parse("sqrt(neg(2.0))"),  # undefined everywhere
        parse("1.0"),  # the box filter again
        parse("distance2(depth, depth)"),  # undefined (zero weight sum) on the first image only
    ]
    fitness = Fitness(feats, color, ref, radius=1, tree_batch=2)
    values = fitness(trees)
    assert values[0] == pytest.approx(expected, rel=1e-12) and values[3] == values[0]
    assert values[1] == pytest.approx(1.0, rel=1e-12)
    assert values[2] == WORST and values[4] == WORST
    assert fitness.evaluations == 5
    assert fitness(trees[:1]) == values[:1] and fitness.evaluations == 6
    # a wider window: radius 2 (5x5 box)
    box2 = _box_np(c, 2)
    value2 = Fitness(feats, color, ref, radius=2)([parse("2.0")])[0]
    assert value2 == pytest.approx(float((_relmse_np(box2, y) / _relmse_np(c, y)).mean()), rel=1e-12)


def test_bias_guard_adds_its_weight_times_each_images_energy_change_against_the_noisy_input():
    """fitness = mean_i [relMSE ratio_i + w |mean(filtered_i) / mean(noisy_i) - 1|], means over pixels and
    channels; w = 0 (the default, the thesis) is the plain fitness. Two filters move each image's mean by
    a different amount, one up, one down (the guard takes the absolute value); the box filter keeps the
    mean, so the guard leaves it alone."""
    from src.gp.evaluate import filter_images

    feats, color, ref = _unequal_noise_images()
    # brightens both images a little (+0.05 %, +0.7 %), darkens both (-0.002 %, -0.13 %), keeps the mean
    trees = [parse(e) for e in ("distance2(color, color)", "exp(neg(distance2(color, color)))", "2.0")]
    trees.append(parse("sqrt(neg(2.0))"))
    plain = Fitness(feats, color, ref, radius=1)(trees)
    guarded = Fitness(feats, color, ref, radius=1, bias_guard=10.0)(trees)
    c, y = color.numpy(), ref.numpy()
    for k, sign in ((0, 1), (1, -1)):
        x = filter_images(trees[k : k + 1], feats, color, 1).color[0].numpy()
        ratios = _relmse_np(x, y) / _relmse_np(c, y)
        bias = x.reshape(2, -1).mean(1) / c.reshape(2, -1).mean(1) - 1
        assert (sign * bias > 1e-5).all() and abs(bias[1]) > 2 * abs(bias[0])  # the fixture bites
        assert plain[k] == pytest.approx(float(ratios.mean()), rel=1e-9)
        assert guarded[k] == pytest.approx(float((ratios + 10.0 * np.abs(bias)).mean()), rel=1e-9)
        assert guarded[k] > plain[k] + 1e-3
    assert guarded[2] == pytest.approx(plain[2], rel=1e-12)  # the box filter keeps each image's mean
    assert guarded[3] == WORST  # undefined stays undefined
    assert Fitness(feats, color, ref, radius=1, bias_guard=0.0)(trees) == plain
    with pytest.raises(ValueError, match="bias_guard=-1"):
        Fitness(feats, color, ref, radius=1, bias_guard=-1.0)
    dark = color.clone()
    dark[1] = -dark[1].abs()  # a noisy image whose mean is negative: the ratio means nothing
    with pytest.raises(DataError, match="bias_guard"):
        Fitness(feats, dark, ref, radius=1, bias_guard=1.0)
    Fitness(feats, dark, ref, radius=1)  # without the guard it is not needed


def test_bias_guard_is_a_search_setting_off_by_default_and_a_negative_weight_is_one_line():
    from omegaconf import OmegaConf

    from src.schema.checks import check
    from src.schema.filter_search import Search

    cfg = compose_config(["task=filter_search"])
    assert cfg.task.search.bias_guard == 0.0
    values = OmegaConf.to_container(cfg.task.search) | {"fitness_eps": 0.01, "seed": 0, "out_dir": "search"}
    check(Search, values, "task.search")  # today's values pass
    values["bias_guard"] = -0.5
    with pytest.raises(ConfigError) as excinfo:
        check(Search, values, "task.search")
    one_line_error(excinfo, "task.search.bias_guard", "-0.5")


def test_fitness_refuses_a_training_image_without_noise():
    feats, color, ref = _unequal_noise_images()
    color = color.clone()
    color[1] = ref[1]  # the second image is its reference: relMSE(noisy) = 0, every ratio undefined
    with pytest.raises(DataError, match="equals its reference"):
        Fitness(feats, color, ref, radius=1)


def test_crossover_exchanges_the_one_common_type_point_exactly():
    """cx_one_point on a 2-node tree and a tree whose only float point below the root is distance2: the
    exchange is forced (the float points are 1.0 and distance2's subtree), in either argument order."""
    pset, _ = _pset_book()
    random.seed(0)
    for _ in range(5):
        a, b = cx_one_point(Individual(parse("neg(1.0)", pset)), Individual(parse(SHORT_VECTOR, pset)))
        assert (str(a), str(b)) == ("neg(distance2(normal, normal))", "exp(1.0)")
        b, a = cx_one_point(Individual(parse(SHORT_VECTOR, pset)), Individual(parse("neg(1.0)", pset)))
        assert (str(a), str(b)) == ("neg(distance2(normal, normal))", "exp(1.0)")
    # a single node has no point below its root: nothing is exchanged
    a, b = cx_one_point(Individual(parse("1.0", pset)), Individual(parse(SHORT_VECTOR, pset)))
    assert (str(a), str(b)) == ("1.0", SHORT_VECTOR)


SHORT_VECTOR = "exp(distance2(normal, normal))"


def test_crossover_draws_the_common_type_then_a_point_of_it_in_each():
    """Both types common: float (the distance subtrees, one point each) or Vector (two terminal points
    each), 1/2 each; a Vector exchange swaps one terminal of each; 2000 draws."""
    pset, _ = _pset_book()
    random.seed(3)
    float_swaps, vector_swaps, draws = 0, {}, 2000
    for _ in range(draws):
        a, b = cx_one_point(
            Individual(parse(SHORT_VECTOR, pset)), Individual(parse("exp(distance1(depth, texture))", pset))
        )
        if str(a) == "exp(distance1(depth, texture))":
            assert str(b) == SHORT_VECTOR
            float_swaps += 1
        else:
            vector_swaps[str(a), str(b)] = vector_swaps.get((str(a), str(b)), 0) + 1
    assert _within(float_swaps, draws, 0.5)
    pairs = {
        (f"exp(distance2({x}, {y}))", f"exp(distance1({u}, {v}))")
        for k, z in enumerate(("depth", "texture"))
        for j in range(2)
        for x, y, u, v in [
            (
                z if j == 0 else "normal",
                z if j == 1 else "normal",
                "normal" if k == 0 else "depth",
                "normal" if k == 1 else "texture",
            )
        ]
    }
    assert set(vector_swaps) == pairs  # each of the 2 x 2 terminal pairs
    for count in vector_swaps.values():
        assert _within(count, draws, 1 / 8)


def test_parent_is_the_nearest_node_above_whose_subtree_holds_the_index():
    from src.gp.variation import _parent

    for text in (SEED, "exp(-distance2(normal, normal))", "mitchell(distance1(depth, texture)) * 0.3"):
        tree = parse(text)
        for i in range(1, len(tree)):
            expected = max(j for j in range(i) if tree.searchSubtree(j).stop > i)
            assert _parent(tree, i) == expected, (text, i)
    with pytest.raises(IndexError):
        _parent(parse("1.0 + 2.0"), 3)


def test_swap_exchanges_two_disjoint_subtrees_adjacent_ones_included():
    """mut_swap with one try on add(1.0, 2.0): of the 9 equally likely point pairs only (1, 2) and (2, 1)
    are type-compatible and disjoint (the adjacent leaves; the root overlaps both): a swap 2/9 of the time;
    with the default 20 tries, all but (7/9)^20 of the time. The node lists are compared, not only the
    texts (DEAP prints a malformed node list as its last complete subtree)."""
    random.seed(4)
    draws = 1800
    one_try = [mut_swap(Individual(parse("1.0 + 2.0")), tries=1)[0] for _ in range(draws)]
    nodes = {tuple(node.name for node in out) for out in one_try}
    assert nodes == {("add", "1.0", "2.0"), ("add", "2.0", "1.0")}
    assert _within(sum(str(out) == "add(2.0, 1.0)" for out in one_try), draws, 2 / 9)
    default = [str(mut_swap(Individual(parse("1.0 + 2.0")))[0]) for _ in range(200)]
    assert default.count("add(2.0, 1.0)") >= 195


def test_swap_draws_again_after_points_of_different_types():
    """exp(distance2(normal, depth)): of the 16 point pairs, 8 are of different types (drawn again), and
    only (2, 3) and (3, 2) swap: with 20 tries a swap 1 - (7/8)^20 = 93% of the time; 400 draws."""
    random.seed(6)
    draws = 400
    outs = [mut_swap(Individual(parse("exp(distance2(normal, depth))")))[0] for _ in range(draws)]
    swapped = [str(out) == "exp(distance2(depth, normal))" for out in outs]
    assert all(s or str(out) == "exp(distance2(normal, depth))" for s, out in zip(swapped, outs, strict=True))
    assert all(len(out) == 4 for out in outs)
    assert _within(sum(swapped), draws, 1 - (7 / 8) ** 20)


def test_relative_error_is_the_per_image_mean_over_pixels_of_the_channel_sum():
    g = torch.Generator().manual_seed(9)
    x = torch.randn(2, 3, 4, 5, generator=g, dtype=torch.float64)
    y = torch.randn(2, 3, 4, 5, generator=g, dtype=torch.float64)
    got = relative_error(x, y, 0.05)
    np.testing.assert_allclose(got.numpy(), _relmse_np(x.numpy(), y.numpy(), eps=0.05), rtol=1e-14)
    assert got.shape == (2,)


def test_island_stats_by_value():
    from src.gp.search import island_stats
    from src.gp.text import to_infix

    island = []
    for text, value in (
        ("1.0", WORST),
        ("neg(2.0)", 0.5),
        ("2.0 * 3.0", 0.25),
        ("5.0", WORST),
        ("7.0", 0.75),
    ):
        ind = Individual(parse(text))
        ind.fitness.values = (value,)
        island.append(ind)
    assert island_stats(island) == {"best": 0.25, "mean": 0.5, "invalid": 2, "best_expression": "2.0 * 3.0"}
    for ind in island:
        ind.fitness.values = (WORST,)
    stats = island_stats(island)
    assert stats == {"best": WORST, "mean": WORST, "invalid": 5, "best_expression": to_infix(island[0])}


def test_a_fitness_that_drops_a_tree_is_an_error():
    search = GPSearch(lambda trees: [0.5] * (len(trees) - 1), SEED, SearchParams(), *_pset_book())
    with pytest.raises(ValueError):
        search.evaluate([Individual(parse("1.0")), Individual(parse("2.0"))])


def test_run_reports_every_generation_and_records_its_history():
    fit = _TextFitness()
    params = SearchParams(islands=2, population=5, generations=3, seed=1)
    seen = []
    state = GPSearch(fit, SEED, params, *_pset_book()).run(on_generation=lambda s: seen.append(s.generation))
    assert seen == [0, 1, 2, 3] and state.generation == 3
    from src.gp.search import island_stats

    assert [h["generation"] for h in state.history] == [0, 1, 2, 3]
    assert state.history[0]["evaluations"] == 10  # generation 0: every individual of both islands
    assert set(state.history[-1]) == {"generation", "evaluations", "islands"}
    assert state.history[-1]["islands"] == [island_stats(island) for island in state.islands]
    more = GPSearch(fit, SEED, SearchParams(**{**params.__dict__, "generations": 5}), *_pset_book())
    seen.clear()
    more.run(state=state, on_generation=lambda s: seen.append(s.generation))
    assert seen == [4, 5]


def test_load_state_refuses_other_files_and_names_only_the_differing_parameters(tmp_path):
    params = SearchParams(islands=1, population=3, generations=0, seed=1)
    state = GPSearch(_TextFitness(), SEED, params, *_pset_book()).run()
    save_state(tmp_path / "s.json", state, params)
    (tmp_path / "other.json").write_text(json.dumps({"format": "something else"}))
    with pytest.raises(DataError, match="not a search checkpoint"):
        load_state(tmp_path / "other.json", params)
    other = SearchParams(**{**params.__dict__, "tournament_size": 3, "seed": 2, "generations": 9})
    with pytest.raises(DataError, match=r"other parameters \(seed, tournament_size\)$"):
        load_state(tmp_path / "s.json", other)


def test_search_grammar_keeps_only_the_available_terminals_and_pixel():
    from src.gp.grammar import PSET, VECTORS

    pset = search_pset(["normal", "nVariance"])
    assert {t.name for t in pset.terminals[Vector]} == {"normal", "pixel"}
    constants = {"0.1", "0.2", "0.3", "0.3333", "1.0", "2.0", "3.0", "pi", "5.0", "7.0", "11.0", "13.0"}
    assert {t.name for t in pset.terminals[float]} == constants | {"nVariance"}
    assert pset.terms_count == 2 + 13
    # untouched: Fig. 3.2's 6 variances and 12 constants, and colorVariance (which the search draws only
    # with color_variance=True)
    assert len(PSET.terminals[Vector]) == len(VECTORS) and PSET.terms_count == len(VECTORS) + 6 + 1 + 12
    assert "colorVariance" not in {t.name for t in search_pset(["normal", "colorVariance"]).terminals[float]}
    with_cv = search_pset(["normal", "colorVariance"], color_variance=True)
    assert {t.name for t in with_cv.terminals[float]} == constants | {"colorVariance"}
    assert "colorVariance" not in {
        t.name for t in search_pset(["normal"], color_variance=True).terminals[float]
    }


def test_kernel_expressions_are_every_kernel_of_every_feature_and_the_gaussian():
    kernels = ("mitchell", "sinc", "epanechnikov", "biweight", "tricube")
    expected = []
    for f in ("normal", "depth"):
        expected += [f"{k}(distance2({f}, {f}))" for k in kernels]
        expected.append(f"exp(-(distance2({f}, {f}) ** 2.0 / (2.0 * 0.1 ** 2.0)))")
    assert kernel_expressions(["normal", "depth"]) == expected


def test_search_parameters_are_checked():
    for bad in (
        {"replication": 0.5},  # shares sum to 1.4
        {"mutation": 0.44},  # 0.99
        {"mutation_kinds": {"hoist": 1.0}},
        {"mutation_kinds": {"insert": 0.0, "swap": 0.0}},
    ):
        with pytest.raises(ValueError):
            SearchParams(**bad)
    SearchParams(replication=0.2, crossover=0.4, mutation=0.4, mutation_kinds={"swap": 1.0, "delete": 0.0})
    seed_length = len(parse(SEED))
    GPSearch(_TextFitness(), SEED, SearchParams(max_length=seed_length), *_pset_book())  # at the limit: fine
    with pytest.raises(ValueError, match="over max_length"):
        GPSearch(_TextFitness(), SEED, SearchParams(max_length=seed_length - 1), *_pset_book())


def test_best_per_island_is_the_lowest_fitness_first_of_equals():
    from src.gp.search import SearchState, best_per_island

    islands = []
    for values in ((3.0, 1.0, 2.0, 1.0), (WORST, 0.5, 0.25)):
        island = []
        for j, value in enumerate(values):
            ind = Individual(parse(f"{float(j + 1)!r}"))
            ind.fitness.values = (value,)
            island.append(ind)
        islands.append(island)
    best = best_per_island(SearchState(islands, 0, random.getstate(), []))
    assert best[0] is islands[0][1] and best[1] is islands[1][2]


def test_a_defined_expression_whose_error_overflows_gets_the_worst_fitness():
    """Negative lobes amplify: weight 1 at the centre and -0.124 at the 8 neighbours sum to 0.008, so a
    float32 spike of 1e18 filters to 1.25e20, finite (the expression is defined on the image), but its
    squared error overflows to inf: the fitness is WORST, not inf."""
    from src.gp.evaluate import filter_images

    ref = torch.full((1, 3, 5, 5), 0.5)
    color = ref.clone()
    color[0, 0, 2, 2] = 1e18
    tree = parse("1.0 - 1.124 * distanceMax(pixel, pixel)")
    result = filter_images([tree], {}, color, 1)
    assert bool(result.valid[0].all())
    assert float(result.color[0][0, 0, 2, 2]) == pytest.approx(1.25e20, rel=1e-3)
    assert Fitness({}, color, ref, radius=1)([tree]) == [WORST]


# Surviving mutants of src/gp/search.py (bash scripts/mutation.sh gp; run before the operators and the
# fitness moved to src/gp/variation.py and src/gp/fitness.py, unchanged), all equivalent here:
# - the search's grammar dropped where a tree is parsed or a constant made (codebook, GPSearch.__init__,
#   load_state: `parse(text, )`; mut_delete: `constant(1.0, )`): the full grammar `PSET` gives the same
#   nodes by name as its deep copy `search_pset(...)`, so the same texts and trees; `gp.mutUniform(...,
#   None)` and `mut_insert(..., None)` (Variation._mutate): the pset only reaches the codebook draw, which
#   ignores it.
# - cx_one_point `len(ind1) < 2 or len(ind2) < 2` -> `and`: a one-node tree has no point below its root, so
#   no common type and nothing is exchanged either way.
# - mut_swap `tries: int = 20` -> 21: one more try after 20 failed ones changes the chance of giving up
#   from (1 - p)^20 to (1 - p)^21, not measurable in a test's draws; `si.start > sj.start` -> `>=`: equal
#   starts are the same subtree, already refused as overlapping.
# - offspring `r < p.replication`, `r < p.replication + p.crossover`, `random() < p.crossover_mutation`
#   -> `<=`: the boundary value of `random.random()` (a multiple of 2^-53) is drawn with probability 2^-53
#   at most.
# - select `selTournament(island, 1, ...)[0]` -> `(island, 2, ...)[0]`: a second tournament is drawn and
#   dropped; the winner has the same law (only the random stream moves on).
# - migrate `selBest(pop, k)` -> `selBest(pop, None)`: `tools.migRing` pairs only the first `migrants`
#   emigrants (the k best, in the same order) with the k replaced.
# - Variation `if w > 0` -> `w >= 0`: a zero weight stays in `random.choices`' cumulative weights but is
#   never drawn, with the same random numbers.
# - Fitness `tree_batch: int = 16` -> 17: the batching changes no value (tree_batch=2 is pinned above);
#   `zip(result.color, result.valid, strict=True)` -> strict None/False/absent: `filter_images` returns
#   the two lists with one entry per tree.
# - SearchParams `abs(total - 1.0) > 1e-6` -> `>=`: only a sum exactly 1e-6 away from 1 tells them apart.
