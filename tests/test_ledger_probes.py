"""The reviewer's probes of the ledger (issue 43), each a hand-made MLflow store on which the pooled-items
ledger gave a status the evidence does not support: deterministic arms scored under three seeds counted
three times, failed outputs dropped, arms trained at different budgets or commits compared without a
word, a run whose budget was overridden counted at its profile. Each test also checks the other side of
its rule (the matched, declared or deterministic case that must still be decided)."""

import math
import textwrap
from dataclasses import replace
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
from mlflow.tracking import MlflowClient

from src.report.claims import parse_claim
from src.report.ledger import LedgerSettings, arm_learned, build_ledger, evaluate_claim, item_scores
from src.report.matched_arms import off_profile_key, profile_keys
from src.report.replication import NESTED, REPLICATE, RUN_FAILED_COLUMN, arm_table, replicate_differences
from src.report.signed_rank import signed_rank
from src.report.verdicts import (
    CONFOUNDED,
    DIRECTION_ONLY,
    NOT_DISTINGUISHABLE,
    NOT_REPRODUCED,
    NOT_RUN,
    REPRODUCED,
    UNDERPOWERED,
)
from tests.conftest import CONF_DIR
from tests.test_ledger import log_run

#: Ten held-out images on which filter a beats filter b in 7 and loses in 3: signed-rank p = 0.19 over
#: the 10 images; counted three times (one per seed) the same numbers give p = 0.017.
TEN = np.array([0.5, 0.8, 1.1, 1.3, 0.4, 0.9, -1.2, -0.3, -0.6, 0.7])
CPU = {"nrbench.profile": "cpu", "nrbench.git_commit": "c0ffee1234", "nrbench.data_fingerprint": "f00d"}
BUDGET = "# @package task\ntrain:\n  epochs: 40\n  max_steps: 10\n"


def _images(values, undefined=None):
    frame = pd.DataFrame({"scene": [f"s{i}" for i in range(len(values))], "spp": 4, "psnr": values})
    return frame.assign(relmse_ratio=0.5, undefined=undefined if undefined is not None else 0.0)


@pytest.fixture(scope="module")
def probe_store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("probe_store")
    previous = mlflow.get_tracking_uri()
    uri = f"sqlite:///{tmp}/mlflow.db"
    mlflow.set_tracking_uri(uri)
    client = MlflowClient()
    exp = client.create_experiment("nrbench-denoise", artifact_location=(tmp / "art").as_uri())

    def study(name, model, seed, images, tags=CPU, status="FINISHED", **params):
        job = params.pop("hydra_job", f"model={model} seed={seed} +sweep={name} profile=cpu")
        params = {"report.name": f"sweeps/{name}", "model.name": model, "seed": seed, **params}
        artifact = None if images is None else ("eval/per_image.csv", images)
        log_run(client, exp, tmp, params, {**tags, "nrbench.hydra_job": job}, None, artifact, status)

    base = 30.0 + np.arange(10.0)
    for seed in range(3):  # two deterministic filters: the same scores under every seed
        study("filters", "filter_a", seed, _images(base + TEN), **{"model.learned": "False"})
        study("filters", "filter_b", seed, _images(base), **{"model.learned": "False"})
        # the same numbers without the config saying so: seen from the identical scores
        study("unmarked", "filter_a", seed, _images(base + TEN))
        study("unmarked", "filter_b", seed, _images(base))
        # filter_b said deterministic by its config though its last digits vary per seed (threads)
        study("jittered", "filter_a", seed, _images(base + TEN), **{"model.learned": "False"})
        study("jittered", "filter_b", seed, _images(base + 0.001 * seed), **{"model.learned": "False"})
        # runs at two profiles besides cpu's (a claim at paper finds neither meaningful)
        for profile in ("cpu", "smoke"):
            tags = {**CPU, "nrbench.profile": profile}
            study("elsewhere", "filter_a", seed, _images(base + TEN), tags)
            study("elsewhere", "filter_b", seed, _images(base), tags)
    # An expression better by 1 dB where defined, undefined on 4 of 10 images (NaN scores).
    failing = np.where(np.arange(10) < 6, base + 1.0, np.nan)
    undefined = np.where(np.arange(10) < 6, 0.0, 1.0)
    for seed in range(3):
        study("failures", "gp_expr", seed, _images(failing, undefined), **{"model.learned": "False"})
        study("failures", "cross_bilateral", seed, _images(base), **{"model.learned": "False"})
    # Trainings that crashed: dpcn's failed on every seed, and seed 0's was requeued and finished (1 dB
    # below kpcn's). In a second study resnet's and kpcn's both failed on seed 1 (a failure on both sides).
    for seed in range(6):
        study("crashes", "kpcn", seed, _images(base + 1.0 + 0.1 * seed))
        study("crashes", "dpcn", seed, None, status="FAILED")
        lost = seed == 1
        for model, gain in (("kpcn", 0.0), ("resnet", 2.0)):
            scores = None if lost else _images(base + gain + 0.1 * seed)
            study("crashes_both", model, seed, scores, status="FAILED" if lost else "FINISHED")
    study("crashes", "dpcn", 0, _images(base))
    # Six seeds of kpcn 1 dB above dpcn, at different epochs; the same at another commit and data.
    for seed in range(6):
        shift = 0.1 * seed
        study("budgets", "kpcn", seed, _images(base + 1 + shift), **{"task.train.epochs": 2})
        study("budgets", "dpcn", seed, _images(base + shift), **{"task.train.epochs": 1})
        study("commits", "kpcn", seed, _images(base + 1 + shift), {**CPU, "nrbench.git_commit": "aaaa111"})
        study("commits", "dpcn", seed, _images(base + shift), {**CPU, "nrbench.git_commit": "bbbb222"})
        study("data", "kpcn", seed, _images(base + 1 + shift), {**CPU, "nrbench.data_fingerprint": "d1"})
        study("data", "dpcn", seed, _images(base + shift), {**CPU, "nrbench.data_fingerprint": "d2"})
        # kpcn trained for 2 epochs, dpcn for 1, each set on the command line (as a study sets its arms)
        for model, epochs, gain in (("kpcn", 2, 1.0), ("dpcn", 1, 0.0)):
            job = f"model={model} seed={seed} +sweep=epochs_cli profile=cpu task.train.epochs={epochs}"
            scores = _images(base + gain + shift)
            study("epochs_cli", model, seed, scores, hydra_job=job, **{"task.train.epochs": epochs})
        # one model's seeds split over two commits
        commit = "aaaa111" if seed < 3 else "bbbb222"
        study("commits_split", "kpcn", seed, _images(base + 1 + shift), {**CPU, "nrbench.git_commit": commit})
        # A cpu-tagged study whose budget was overridden on the command line (each arm moved another key),
        # and one that swept an arm key.
        overridden = f"model=kpcn seed={seed} +sweep=shrunk profile=cpu task.train.epochs=1"
        study("shrunk", "kpcn", seed, _images(base + 1 + shift), hydra_job=overridden)
        study(
            "shrunk",
            "dpcn",
            seed,
            _images(base + shift),
            hydra_job=f"model=dpcn seed={seed} +sweep=shrunk profile=cpu task.train.max_steps=5",
        )
        for whiten in ("true", "false"):
            job = f"model.whiten={whiten} seed={seed} +sweep=whitening profile=cpu"
            scores = _images(base + shift + (1.0 if whiten == "true" else 0.0))
            study("whitening", "kpcn", seed, scores, hydra_job=job, **{"model.whiten": whiten})
        # LPIPS scored with the trained weights (x, y; r off the profile's budget) and with the random trunk
        # (p, q; s off the budget too), in a column `lpips` and one named as the runs' metric, `eval_lpips`.
        trained, untrained = "vgg16(w.pth)+lin(l.pth)", "vgg16-random(seed=0)+lin-uniform"
        for model, variant, offset, off in (
            ("x", trained, 0.0, ""),
            ("y", trained, 0.1, ""),
            ("p", untrained, 0.0, ""),
            ("q", untrained, 0.1, ""),
            ("s", untrained, 0.2, " task.train.epochs=1"),
            ("r", trained, 0.05, " task.train.epochs=1"),
        ):
            value = 0.2 + offset + 0.01 * seed
            scores = _images(base).assign(lpips=value, eval_lpips=value)
            job = f"model={model} seed={seed} +sweep=lpips profile=cpu{off}"
            study("lpips", model, seed, scores, {**CPU, "nrbench.lpips_variant": variant}, hydra_job=job)
        # A filter search (gp_filter is "not learned", but the expression found is the seed's) with its
        # constant-sigma baseline scored beside it on the same images.
        found = _images(base + 0.5 + 0.2 * seed).assign(baseline_psnr=base)
        search = {"task.name": "filter_search", "model.learned": "False"}
        study("search", "gp_filter", seed, found, **search)
        # the same search undefined on two held-out images (its baseline is defined on all ten)
        undefined = np.where(np.arange(10) < 2, 1.0, 0.0)
        failing = found.assign(psnr=np.where(undefined > 0, np.nan, found["psnr"]), undefined=undefined)
        study("search_failing", "gp_filter", seed, failing, **search)
        # Two NeRF-like models whose own recipes differ (precrop warm-up, and steps: a budget key).
        for model, precrop, steps in (("nerf", 100, 12), ("mipnerf", 0, 10)):
            recipe = {"task.train.precrop_iters": precrop, "task.train.max_steps": steps}
            study(
                "recipes", model, seed, _images(base + (0.3 if model == "mipnerf" else 0.0) + shift), **recipe
            )
        # Feature selection: the features each arm feeds are derived from it (and the random arm's subset
        # from the seed), so they differ between and within arms without being a confound.
        for order, features, gain in (
            ("greedy", '["normal", "depth"]', 0.5),
            ("random", f'["f{seed}", "g"]', 0.0),
        ):
            arm = {"dataset.feature_selection.order": order, "dataset.volume_features": features}
            arm["dataset.feature_selection.random_seed"] = seed if order == "random" else 0
            study("selection", "unet_kpcn", seed, _images(base + gain + shift), **arm)
    yield {"tmp": tmp, "uri": uri}
    mlflow.set_tracking_uri(previous)


def _claim(study, a, b, metric="psnr", kind="better", extra="", higher=True):
    return _rule_claim(study, f"{{kind: {kind}, a: {a}, b: {b}{extra}}}", metric, higher)


def _rule_claim(study, rule, metric="psnr", higher=True):
    """A per-image claim on `study`'s runs at cpu with the `rule` given as YAML flow text."""
    text = textwrap.dedent(
        f"""
        id: probe_{study}
        category: finding
        source: {{document: Davletaliyev 2016, section: "4", quote: q}}
        statement: a beats b.
        profiles: [cpu]
        runs: {{study: {study}, experiment: nrbench-denoise}}
        metric: {metric}
        per: image
        higher: {str(higher).lower()}
        rule: {rule}
        """
    )
    import yaml

    return parse_claim(yaml.safe_load(text), 0)


def _settings(tmp_path, **kw):
    conf = tmp_path / "conf"
    (conf / "task_profile").mkdir(parents=True, exist_ok=True)
    (conf / "task_profile" / "denoise_cpu.yaml").write_text(BUDGET)
    return LedgerSettings(alpha=0.05, all_profiles=("cpu",), budget_keys=profile_keys(conf), **kw)


def test_deterministic_arms_count_each_image_once(probe_store, tmp_path):
    for study in ("filters", "unmarked"):  # said by the config, or seen in the scores
        row = evaluate_claim(
            _claim(study, "{model.name: filter_a}", "{model.name: filter_b}"), _settings(tmp_path)
        )
        assert row.replicates.unit == "images" and row.verdict.items == 10, study
        assert row.replicates.deterministic == (True, True)
        assert (
            row.verdict.p_value == pytest.approx(signed_rank(TEN).p_value) == pytest.approx(0.193, abs=1e-3)
        )
        assert row.verdict.status == NOT_DISTINGUISHABLE  # pooled over 3 x 10 it read "reproduced"
        assert "deterministic arms: each image once, though scored under 3 seed(s)" in row.verdict.numbers


def test_an_arm_said_deterministic_counts_each_image_once_though_its_scores_vary(probe_store, tmp_path):
    """Either arm's `model.learned` decides, not only the first's: filter_b's scores differ per seed in
    the third decimal, and its config says it is deterministic, so the images are the replicates."""
    row = evaluate_claim(
        _claim("jittered", "{model.name: filter_a}", "{model.name: filter_b}"), _settings(tmp_path)
    )
    assert row.replicates.deterministic == (True, True)
    assert row.replicates.unit == "images" and row.verdict.items == 10
    # the scores alone would read filter_b as learned: replicated by its 3 seeds
    a = pd.concat([_images(30 + np.arange(10.0) + TEN).assign(**{"params.seed": s}) for s in range(3)])
    b = pd.concat([_images(30 + np.arange(10.0) + 0.001 * s).assign(**{"params.seed": s}) for s in range(3)])
    seen = replicate_differences(a.assign(value=a["psnr"]), b.assign(value=b["psnr"]), "image", True, False)
    assert seen.deterministic == (True, False) and seen.unit == "seeds"


@pytest.mark.parametrize(
    "runs, learned",
    [
        ({"params.model.learned": ["True", " true "]}, True),  # the config's spelling, any case or padding
        ({"params.model.learned": ["FALSE", "False"]}, False),
        ({"params.model.learned": ["True", "False"]}, None),  # the runs disagree: the scores decide
        ({"params.model.learned": ["maybe", "maybe"]}, None),
        ({"params.model.learned": [None, None]}, None),
        ({"params.model.learned": ["True", None]}, True),  # a run that did not log it: the others say
        ({"params.seed": ["0", "1"]}, None),  # not logged
        (
            {"params.task.name": ["filter_search"] * 2, "params.model.learned": ["False"] * 2},
            True,
        ),  # a search
        ({"params.task.name": ["filter_search", "denoise"], "params.model.learned": ["False"] * 2}, False),
    ],
)
def test_an_arms_learned_flag_is_what_all_its_runs_log(runs, learned):
    assert arm_learned(pd.DataFrame(runs)) is learned
    assert arm_learned(pd.DataFrame(runs).iloc[0:0]) is None  # no runs say nothing


def test_a_comparable_claim_over_seeds_states_the_images_nested_in_each(probe_store, tmp_path):
    extra = ", tolerance: 2, tolerance_source: ours"
    claim = _claim(
        "whitening", '{model.whiten: "true"}', '{model.whiten: "false"}', kind="comparable", extra=extra
    )
    row = evaluate_claim(claim, _settings(tmp_path))
    assert row.verdict.status == REPRODUCED  # whitening is 1 dB ahead on every seed: within 2 dB
    assert row.verdict.numbers == (
        "whiten=true - whiten=false = +1 (Hodges-Lehmann), 95% interval [+1, +1] over 6 seeds "
        "(10 item(s) nested in each), tolerance ±2"
    )


def test_a_not_worse_claim_over_seeds_states_the_images_nested_in_each_and_a_log_margin_as_a_factor(
    probe_store, tmp_path
):
    extra = ", tolerance: 0.5, tolerance_source: ours"
    claim = _claim(
        "whitening", '{model.whiten: "false"}', '{model.whiten: "true"}', kind="not_worse", extra=extra
    )
    row = evaluate_claim(claim, _settings(tmp_path))
    assert row.verdict.status == NOT_REPRODUCED  # 1 dB behind on every seed: more than the 0.5 margin
    assert row.verdict.numbers == (
        "whiten=false ahead of whiten=true by -1 (Hodges-Lehmann), 95% interval [-1, -1] over 6 seeds "
        "(10 item(s) nested in each); margin: at most 0.5 behind"
    )
    logged = replace(claim, log=True, rule=replace(claim.rule, tolerance=math.log(2)))
    numbers = evaluate_claim(logged, _settings(tmp_path)).verdict.numbers
    assert "x (Hodges-Lehmann), 95% interval [" in numbers and numbers.endswith("; margin: at most 2x behind")


def test_a_claim_not_run_at_its_profile_names_every_other_profile_with_runs(probe_store, tmp_path):
    claim = replace(
        _claim("elsewhere", "{model.name: filter_a}", "{model.name: filter_b}"), profiles=("paper",)
    )
    settings = replace(_settings(tmp_path), all_profiles=("paper", "cpu", "smoke"))
    row = evaluate_claim(claim, settings)
    assert row.verdict.status == NOT_RUN
    assert row.verdict.numbers.startswith(
        "no runs at paper; runs at cpu, smoke only, where it is not meaningful; to run (cheapest first): "
    ), row.verdict.numbers


def test_a_learned_arm_is_replicated_by_its_seeds_and_three_are_underpowered(probe_store, tmp_path):
    # The same data with filter_a's scores jittered per seed: a learned arm, three replicates.
    rng = np.random.default_rng(1)
    a = pd.concat(
        [
            _images(30 + np.arange(10.0) + TEN + rng.normal(0, 0.01, 10)).assign(**{"params.seed": s})
            for s in range(3)
        ]
    )
    b = pd.concat([_images(30 + np.arange(10.0)).assign(**{"params.seed": s}) for s in range(3)])
    reps = replicate_differences(a.assign(value=a["psnr"]), b.assign(value=b["psnr"]), "image", True, False)
    assert (reps.unit, reps.seeds, reps.images, len(reps.difference)) == ("seeds", 3, 10, 3)
    assert reps.deterministic == (False, True)
    assert np.allclose(reps.difference, TEN.mean(), atol=0.01)  # each seed: the mean over its 10 images


def test_a_failed_output_is_its_arms_worst_outcome_not_a_dropped_item(probe_store, tmp_path):
    claim = _claim("failures", "{model.name: gp_expr}", "{model.name: cross_bilateral}")
    row = evaluate_claim(claim, _settings(tmp_path))
    assert row.replicates.undefined == (12, 0)  # 4 images x 3 seeds counted; 4 images once in the test
    assert (
        row.verdict.items == 10 and row.verdict.status == NOT_DISTINGUISHABLE
    )  # dropped: 6 of 6 for gp_expr
    assert "6 favour gp_expr, 4 cross_bilateral" in row.verdict.numbers


def test_a_failed_training_is_its_arms_loss_on_that_seed_unless_a_rerun_finished(probe_store, tmp_path):
    """dpcn's trainings failed on seeds 1-5 (seed 0's rerun finished): dropped, kpcn's win would rest on
    one seed (underpowered); counted, each is dpcn's worst outcome (+inf for kpcn), as the thesis scores
    an undefined expression. Where both arms' runs failed on a seed, that seed is a tie (0)."""
    row = evaluate_claim(_claim("crashes", "{model.name: kpcn}", "{model.name: dpcn}"), _settings(tmp_path))
    d = row.replicates.difference
    assert row.verdict.status == REPRODUCED and row.replicates.unit == "seeds" and len(d) == 6
    assert d.iloc[0] == pytest.approx(1.0) and np.isinf(d.iloc[1:]).all() and (d.iloc[1:] > 0).all()
    assert row.replicates.undefined == (0, 5)
    assert len(row.run_ids) == 6 + 1 + 5  # kpcn's, dpcn's rerun and its five failed runs
    reverse = evaluate_claim(
        _claim("crashes", "{model.name: dpcn}", "{model.name: kpcn}"), _settings(tmp_path)
    )
    assert reverse.verdict.status == NOT_REPRODUCED
    both = evaluate_claim(
        _claim("crashes_both", "{model.name: resnet}", "{model.name: kpcn}"), _settings(tmp_path)
    )
    d = both.replicates.difference
    assert len(d) == 6 and d.iloc[1] == 0.0 and np.allclose(d.drop(d.index[1]), 2.0)
    assert both.replicates.undefined == (1, 1)


def test_arms_trained_at_different_budgets_are_confounded_unless_the_claim_declares_it(probe_store, tmp_path):
    a, b = "{model.name: kpcn}", "{model.name: dpcn}"
    row = evaluate_claim(_claim("budgets", a, b), _settings(tmp_path))
    assert row.verdict.status == CONFOUNDED and "task.train.epochs differs (1.0, 2.0)" in row.verdict.numbers
    declared = evaluate_claim(
        _claim("budgets", a, b, extra=", ratio: {task.train.epochs: 0.5}"), _settings(tmp_path)
    )
    assert (
        declared.verdict.status == REPRODUCED and declared.arm_budget == "task.train.epochs: kpcn 2; dpcn 1"
    )
    wrong = evaluate_claim(
        _claim("budgets", a, b, extra=", ratio: {task.train.epochs: 2}"), _settings(tmp_path)
    )
    assert wrong.verdict.status == CONFOUNDED and "the claim declares 2" in wrong.verdict.numbers
    # A study under way: one arm has no run yet. The claim says so; the ratio check does not fail on it.
    absent = evaluate_claim(
        _claim("budgets", a, "{model.name: resnet}", extra=", ratio: {task.train.epochs: 0.5}"),
        _settings(tmp_path),
    )
    assert absent.verdict.status == NOT_RUN and "no psnr scores for arm resnet" in absent.verdict.numbers


def test_runs_at_another_commit_or_on_other_data_are_confounded(probe_store, tmp_path):
    a, b = "{model.name: kpcn}", "{model.name: dpcn}"
    commits = evaluate_claim(_claim("commits", a, b), _settings(tmp_path))
    assert (
        commits.verdict.status == CONFOUNDED
        and "code commit differs (aaaa111, bbbb222)" in commits.verdict.numbers
    )
    same_code = _settings(tmp_path, equivalent_commits=(("aaaa111", "bbbb222"),))
    assert evaluate_claim(_claim("commits", a, b), same_code).verdict.status == REPRODUCED
    data = evaluate_claim(_claim("data", a, b), _settings(tmp_path))
    assert data.verdict.status == CONFOUNDED and "data fingerprint differs (d1, d2)" in data.verdict.numbers


def test_a_run_whose_budget_was_overridden_does_not_count_at_its_profile(probe_store, tmp_path):
    row = evaluate_claim(_claim("shrunk", "{model.name: kpcn}", "{model.name: dpcn}"), _settings(tmp_path))
    assert row.verdict.status == NOT_RUN
    assert (
        "12 run(s) not counted, off the profile's budget (task.train.epochs, task.train.max_steps overridden)"
        in row.verdict.numbers
    )
    # A budget key the claim compares (its arm) or declares (rule.ratio) may be set on the command line.
    a, b = "{model.name: kpcn}", "{model.name: dpcn}"
    declared = evaluate_claim(
        _claim("epochs_cli", a, b, extra=", ratio: {task.train.epochs: 0.5}"), _settings(tmp_path)
    )
    assert declared.verdict.status == REPRODUCED and declared.not_counted == ""
    undeclared = evaluate_claim(_claim("epochs_cli", a, b), _settings(tmp_path))
    assert undeclared.verdict.status == NOT_RUN and "off the profile's budget" in undeclared.verdict.numbers
    by_epochs = evaluate_claim(
        _claim("epochs_cli", "{task.train.epochs: '2'}", "{task.train.epochs: '1'}"), _settings(tmp_path)
    )
    assert by_epochs.not_counted == "" and by_epochs.verdict.status == CONFOUNDED  # model.name differs too
    assert "model.name differs" in by_epochs.verdict.numbers
    # A study that sweeps a key as its arm is at the profile's budget.
    whiten = evaluate_claim(
        _claim("whitening", "{model.whiten: 'true'}", "{model.whiten: 'false'}"), _settings(tmp_path)
    )
    assert whiten.verdict.status == REPRODUCED and whiten.not_counted == ""


def test_an_lpips_claim_reads_only_runs_with_the_trained_weights(probe_store, tmp_path):
    trained = evaluate_claim(
        _claim("lpips", "{model.name: x}", "{model.name: y}", metric="lpips"), _settings(tmp_path)
    )
    assert trained.verdict.status == NOT_REPRODUCED and trained.not_counted == ""  # higher: true, x is lower
    random = evaluate_claim(
        _claim("lpips", "{model.name: p}", "{model.name: q}", metric="lpips"), _settings(tmp_path)
    )
    assert random.verdict.status == NOT_RUN
    assert "12 run(s) not counted: LPIPS without the trained weights" in random.verdict.numbers
    # the runs' own metric name (eval_lpips) is LPIPS too
    named = evaluate_claim(
        _claim("lpips", "{model.name: p}", "{model.name: q}", metric="eval_lpips"), _settings(tmp_path)
    )
    assert named.verdict.status == NOT_RUN
    assert "at cpu: 12 run(s) not counted: LPIPS without the trained weights; to run" in named.verdict.numbers
    # a run dropped for its weights is not counted again as off the budget
    untrained = evaluate_claim(
        _claim("lpips", "{model.name: p}", "{model.name: s}", metric="lpips"), _settings(tmp_path)
    )
    assert untrained.verdict.status == NOT_RUN
    assert "12 run(s) not counted: LPIPS without the trained weights" in untrained.verdict.numbers
    assert "off the profile's budget" not in untrained.verdict.numbers
    # Runs dropped for both reasons: one note each.
    both = evaluate_claim(
        _claim("lpips", "{model.name: p}", "{model.name: r}", metric="lpips"), _settings(tmp_path)
    )
    assert (
        both.verdict.status == NOT_RUN
        and (
            "6 run(s) not counted: LPIPS without the trained weights; "
            "6 run(s) not counted, off the profile's budget (task.train.epochs overridden)"
        )
        in both.verdict.numbers
    )
    # Another metric of the same runs does not care about the LPIPS weights.
    psnr = evaluate_claim(_claim("lpips", "{model.name: p}", "{model.name: q}"), _settings(tmp_path))
    assert psnr.verdict.status == NOT_DISTINGUISHABLE and psnr.replicates.unit == "images"


@pytest.mark.parametrize(
    ("a", "b", "size", "status"),
    [
        ("x", "y", 0.05, REPRODUCED),  # x's LPIPS is 0.1 lower on every item: beyond the size
        ("x", "y", 0.1, REPRODUCED),  # the interval [0.1, 0.1] reaches the size: consistent with it
        ("x", "y", 0.2, DIRECTION_ONLY),  # lower, but by less than the published 0.2
        ("y", "x", 0.05, NOT_REPRODUCED),  # the other way round
    ],
)
def test_a_lower_is_better_claim_with_a_published_size_reads_both_sides(
    probe_store, tmp_path, a, b, size, status
):
    claim = _claim(
        "lpips",
        f"{{model.name: {a}}}",
        f"{{model.name: {b}}}",
        "lpips",
        extra=f", size: {size}",
        higher=False,
    )
    row = evaluate_claim(claim, _settings(tmp_path))
    assert row.verdict.status == status, row.verdict.numbers
    assert row.verdict.estimate == pytest.approx(0.1 if a == "x" else -0.1)  # a's advantage, lower = better


def test_a_search_is_replicated_by_its_seeds_though_its_model_is_not_trained(probe_store, tmp_path):
    claim = _claim(
        "search", "{model.name: gp_filter}", "{model.name: gp_filter}", extra=", b_metric: baseline_psnr"
    )
    row = evaluate_claim(claim, _settings(tmp_path))
    assert row.replicates.unit == "seeds" and row.replicates.deterministic == (False, True)
    assert row.verdict.items == 6 and row.verdict.status == REPRODUCED


def test_a_baseline_scored_beside_a_search_does_not_share_its_undefined_outputs(probe_store, tmp_path):
    claim = _claim(
        "search_failing",
        "{model.name: gp_filter}",
        "{model.name: gp_filter}",
        extra=", b_metric: baseline_psnr",
    )
    row = evaluate_claim(claim, _settings(tmp_path))
    assert row.replicates.undefined == (12, 0)  # the search's 2 images x 6 seeds; none of the baseline's


def test_a_models_own_recipe_belongs_to_its_arm_and_its_budget_keys_are_shown(probe_store, tmp_path):
    claim = _claim("recipes", "{model.name: mipnerf}", "{model.name: nerf}")
    bare = evaluate_claim(claim, _settings(tmp_path))
    assert bare.verdict.status == CONFOUNDED and "task.train.max_steps differs" in bare.verdict.numbers
    owned = {"nerf": frozenset({"task.train.precrop_iters", "task.train.max_steps"}), "mipnerf": frozenset()}
    row = evaluate_claim(claim, _settings(tmp_path, model_keys=owned))
    assert row.verdict.status == REPRODUCED
    assert row.arm_budget == "task.train.max_steps: mipnerf 10; nerf 12"  # a budget key: shown
    assert "precrop" not in row.arm_budget  # a recipe key outside the budget: the arm's own


def test_keys_derived_from_the_arm_are_the_arms_own(probe_store, tmp_path, monkeypatch):
    claim = _claim(
        "selection", "{dataset.feature_selection.order: greedy}", "{dataset.feature_selection.order: random}"
    )
    row = evaluate_claim(claim, _settings(tmp_path))
    assert row.verdict.status == REPRODUCED, row.verdict.numbers
    # Not declared as derived, the same keys are a confound.
    import src.report.matched_arms as matched_arms

    monkeypatch.setattr(matched_arms, "DERIVED_FROM", {})
    bare = evaluate_claim(claim, _settings(tmp_path))
    assert (
        bare.verdict.status == CONFOUNDED and "dataset.feature_selection.random_seed" in bare.verdict.numbers
    )


def test_a_random_baseline_must_hold_the_draws_the_claim_asks_for(probe_store, tmp_path):
    """The random arm drew its subset per seed (6 draws): enough for b_distinct 5 or 6, not for 7; the
    greedy arm's single subset would be one draw."""
    a, b = "{dataset.feature_selection.order: greedy}", "{dataset.feature_selection.order: random}"
    for needed, status in ((5, REPRODUCED), (6, REPRODUCED), (7, UNDERPOWERED)):
        claim = _claim("selection", a, b, extra=f", b_distinct: {{dataset.volume_features: {needed}}}")
        row = evaluate_claim(claim, _settings(tmp_path))
        assert row.verdict.status == status, (needed, row.verdict.numbers)
    assert row.verdict.numbers.endswith(
        "arm order=random holds 6 distinct dataset.volume_features over 6 run(s); the claim needs 7 or more "
        "(rule.b_distinct): one draw stands for no distribution of draws"
    ), row.verdict.numbers
    # every key is checked, and a key the runs never logged holds no draw
    two = ", b_distinct: {dataset.volume_features: 6, dataset.never_logged: 2}"
    row = evaluate_claim(_claim("selection", a, b, extra=two), _settings(tmp_path))
    assert (
        row.verdict.status == UNDERPOWERED and "holds 0 distinct dataset.never_logged" in row.verdict.numbers
    )
    one_draw = _claim("selection", b, a, extra=", b_distinct: {dataset.volume_features: 2}")
    row = evaluate_claim(one_draw, _settings(tmp_path))
    assert row.verdict.status == UNDERPOWERED and "holds 1 distinct" in row.verdict.numbers


def test_off_profile_keys_read_the_overrides():
    budget = frozenset({"task.train.epochs", "dataset.noisy_spp"})
    assert off_profile_key("model=kpcn seed=1 profile=cpu", budget, []) == ""
    assert off_profile_key("model=kpcn task.train.epochs=3", budget, []) == "task.train.epochs"
    assert off_profile_key("++dataset.noisy_spp=2", budget, []) == "dataset.noisy_spp"
    assert off_profile_key("task.train={epochs:3}", budget, []) == "task.train"  # a whole subtree
    assert off_profile_key("task_profile=denoise_smoke", budget, []) == "task_profile"
    assert off_profile_key("task.train.epochs=3", budget, ["task.train.epochs"]) == ""  # the claim's arm
    assert off_profile_key(float("nan"), budget, []) == ""  # a run that logged no overrides


def test_profile_keys_are_every_leaf_a_profile_file_sets(tmp_path):
    (tmp_path / "task_profile").mkdir()
    (tmp_path / "task_profile" / "denoise_cpu.yaml").write_text(
        "# @package task\ntrain:\n  epochs: 4\n  lr: 1\n"
    )
    (tmp_path / "dataset_profile").mkdir()
    (tmp_path / "dataset_profile" / "procedural_cpu.yaml").write_text(
        "# @package dataset\nnoisy_spp: [1, 2]\n"
    )
    (tmp_path / "profile").mkdir()
    (tmp_path / "profile" / "cpu.yaml").write_text("# @package _global_\nprofile_name: cpu\n")
    assert profile_keys(tmp_path) == {
        "task.train.epochs",
        "task.train.lr",
        "dataset.noisy_spp",
        "profile_name",
    }


def test_the_real_profiles_set_the_training_budget():
    from tests.conftest import ROOT

    keys = profile_keys(ROOT / "conf")
    assert {"task.train.epochs", "dataset.noisy_spp"} <= keys


def test_a_study_family_is_adjusted_together(probe_store, tmp_path):
    conf = tmp_path / "conf"
    (conf / "profile").mkdir(parents=True)
    (conf / "profile" / "cpu.yaml").write_text("{}\n")
    claims = [
        ("budgets_ok", "budgets", "ratio: {task.train.epochs: 0.5}"),
        ("budgets_again", "budgets", "ratio: {task.train.epochs: 0.5}, size: 0.5"),
        ("budgets_target", "budgets", "ratio: {task.train.epochs: 0.5}"),  # a target: not in the family
    ]
    text = "claims:\n" + "".join(
        textwrap.indent(
            textwrap.dedent(
                f"""
                - id: {cid}
                  category: {"target" if cid.endswith("target") else "finding"}
                  source: {{document: Davletaliyev 2016, quote: q}}
                  statement: s.
                  profiles: [cpu]
                  runs: {{study: {study}, experiment: nrbench-denoise}}
                  metric: psnr
                  per: image
                  higher: true
                  rule: {{kind: better, a: {{model.name: kpcn}}, b: {{model.name: dpcn}}, {extra}}}
                """
            ),
            "  ",
        )
        for cid, study, extra in claims
    )
    (conf / "claims.yaml").write_text(text)
    from omegaconf import OmegaConf

    cfg = OmegaConf.create(
        {
            "ledger": {"claims": str(conf / "claims.yaml"), "out_dir": str(tmp_path / "out"), "alpha": 0.05},
            "tracking": {"uri": probe_store["uri"]},
            "report": {"site": False},
        }
    )
    summary = build_ledger(cfg)
    frame = pd.read_csv(summary["paths"]["csv"]).set_index("claim")
    statuses = {"budgets_ok": REPRODUCED, "budgets_again": REPRODUCED, "budgets_target": REPRODUCED}
    assert summary["statuses"] == statuses, frame["numbers"].tolist()
    frame = pd.read_csv(summary["paths"]["csv"]).set_index("claim")
    assert frame.loc["budgets_ok", "family"] == "study budgets at cpu (2 tests)"
    assert float(frame.loc["budgets_ok", "p_adjusted"]) == pytest.approx(0.031, abs=1e-3)
    assert frame.loc["budgets_target", "family"] == "-" and frame.loc["budgets_target", "p_adjusted"] == "-"
    assert summary["counts"] == "2 reproduced"  # the headline counts findings and readings only


def _arm(values_by_seed, undefined_by_seed=None):
    """Scores as the ledger passes them: one row per (seed, image), `value` and `failed`."""
    parts = []
    for seed, values in values_by_seed.items():
        frame = _images(np.asarray(values, float)).assign(**{"params.seed": seed})
        failed = (undefined_by_seed or {}).get(seed, np.zeros(len(values)))
        parts.append(frame.assign(value=frame["psnr"], failed=np.asarray(failed) > 0))
    return pd.concat(parts, ignore_index=True)


def _two_rows(column: str, per: str) -> pd.DataFrame:
    """Two scores alike in every key column but `column` (values 1 and 3), with a column outside the key."""
    base = {c: "x" for c in (*REPLICATE, *NESTED[per])} | {"model.name": "m", "value": 1.0}
    return pd.DataFrame([base, base | {column: "y", "value": 3.0}])


@pytest.mark.parametrize(
    ("per", "column"), [("image", c) for c in NESTED["image"]] + [("run", *NESTED["run"])]
)
def test_each_field_of_an_item_key_tells_two_items_apart(per, column):
    table = arm_table(_two_rows(column, per), per)
    assert len(table) == 2 and sorted(table["value"]) == [1.0, 3.0]
    assert table.index.get_level_values("replicate").nunique() == 1


@pytest.mark.parametrize("column", REPLICATE)
def test_each_field_of_a_replicate_key_tells_two_replicates_apart(column):
    table = arm_table(_two_rows(column, "image"), "image")
    assert table.index.get_level_values("replicate").nunique() == 2
    assert table.index.get_level_values("item").nunique() == 1


def test_a_column_outside_the_keys_is_one_item_scored_twice_and_averaged():
    table = arm_table(_two_rows("model.name", "image"), "image")
    assert len(table) == 1 and table["value"].iloc[0] == 2.0


def test_one_seed_of_deterministic_arms_still_counts_its_images_and_of_learned_arms_does_not():
    a, b = _arm({0: 30 + TEN}), _arm({0: np.full(10, 30.0)})
    said = replicate_differences(a, b, "image", True, False, learned=(False, False))
    assert (said.unit, len(said.difference)) == ("images", 10)  # the pipeline's one run of two filters
    unknown = replicate_differences(a, b, "image", True, False)  # one seed: the scores cannot tell
    assert (unknown.unit, len(unknown.difference)) == ("seeds", 1)


def test_scores_that_never_share_an_image_across_seeds_do_not_make_an_arm_deterministic():
    a = _arm({0: [1.0, 2.0], 1: [3.0, 4.0]}).assign(scene=["s0", "s1", "s2", "s3"])
    b = _arm({0: [0.0, 0.0], 1: [0.0, 0.0]}).assign(scene=["s0", "s1", "s2", "s3"])
    assert replicate_differences(a, b, "image", True, False).deterministic == (False, False)


def test_an_arm_said_to_be_learned_stays_replicated_by_seed_when_its_scores_repeat():
    """Counts (a feature's occurrences) can come out equal under every seed: the config's `learned` still
    decides, and only where it says nothing do equal scores make an arm deterministic."""
    same = _arm({s: [2.0, 2.0] for s in range(6)})
    other = _arm({s: [1.0 + s, 2.0] for s in range(6)})
    assert replicate_differences(same, other, "image", True, False, (True, None)).deterministic == (
        False,
        False,
    )
    seen = replicate_differences(same, other, "image", True, False)
    assert seen.deterministic == (True, False) and (seen.unit, len(seen.difference)) == ("seeds", 6)


def test_a_deterministic_arm_scored_once_pairs_with_every_seed_of_the_learned_arm():
    a = _arm({s: 31 + 0.1 * s + np.arange(10.0) for s in range(6)})
    b = _arm({0: 30 + np.arange(10.0)})
    reps = replicate_differences(a, b, "image", True, False, learned=(True, False))
    assert (reps.unit, len(reps.difference)) == ("seeds", 6)
    assert np.allclose(sorted(reps.difference), [1.0 + 0.1 * s for s in range(6)])


def test_both_arms_failing_on_an_item_is_a_tie():
    fail = {0: [0, 0, 1]}
    a, b = _arm({0: [2.0, 2.0, np.nan]}, fail), _arm({0: [1.0, 1.0, np.nan]}, fail)
    reps = replicate_differences(a, b, "image", True, False, learned=(False, False))
    assert list(reps.difference) == [1.0, 1.0, 0.0] and reps.undefined == (1, 1)
    one = replicate_differences(a, _arm({0: [1.0, 1.0, 1.0]}), "image", True, False, learned=(False, False))
    assert list(one.difference) == [1.0, 1.0, -np.inf]
    lower = replicate_differences(
        a, _arm({0: [1.0, 1.0, 1.0]}), "image", False, False, learned=(False, False)
    )
    assert list(lower.difference)[-1] == np.inf  # lower is better: a failure is +inf in a - b


def _lost_run(seed):
    """A run of `seed` that failed as a whole: one row, no item (src.report.ledger.item_scores)."""
    row = {"params.seed": [seed], "value": [np.nan], "failed": [True], RUN_FAILED_COLUMN: [True]}
    return pd.DataFrame(row)


def _with_lost(arm, seed):
    # As in the ledger, where every run's rows are one frame: the failed run's missing spp makes the
    # column float for all, so the other arm's spp is float too (`_float_spp`).
    return pd.concat([arm, _lost_run(seed)], ignore_index=True)


def _float_spp(arm):
    return arm.astype({"spp": float})


def test_a_failed_run_counts_only_on_a_seed_the_other_arm_has_and_a_baseline_has_every_seed():
    a = _with_lost(_arm({s: 31 + 0.1 * s + np.arange(3.0) for s in range(5)}), 5)
    b = _float_spp(_arm({s: 30 + np.arange(3.0) + 0.01 * s for s in range(5)}))  # learned, no seed 5
    reps = replicate_differences(a, b, "image", True, False)
    assert len(reps.difference) == 5 and np.isfinite(reps.difference).all() and reps.undefined == (1, 0)
    baseline = _float_spp(_arm({0: 30 + np.arange(3.0)}))  # deterministic: it scored seed 5's images too
    reps = replicate_differences(a, baseline, "image", True, False, learned=(True, False))
    assert len(reps.difference) == 6 and reps.difference.iloc[-1] == -np.inf
    lower = replicate_differences(a, baseline, "image", False, False, learned=(True, False))
    assert lower.difference.iloc[-1] == np.inf  # lower is better: a's loss is +inf in a - b
    # Both arms deterministic: the images are the replicates, and a failed run stands for none of them.
    alone = _with_lost(_arm({0: 31 + np.arange(3.0)}), 1)
    both = replicate_differences(alone, baseline, "image", True, False, (False, False))
    assert (both.unit, len(both.difference), both.undefined) == ("images", 3, (1, 0))


def test_each_failed_run_counts_though_an_earlier_one_had_no_counterpart():
    """a's runs of seeds 1 and 4 failed; b has no seed 1 (left out) but has seed 4 (a's loss there)."""
    scored = _arm({s: 31 + 0.1 * s + np.arange(3.0) for s in (0, 2, 3)})
    a = pd.concat([scored, _lost_run(1), _lost_run(4)], ignore_index=True)
    b = _float_spp(_arm({s: 30 + np.arange(3.0) + 0.01 * s for s in (0, 2, 3, 4)}))  # learned
    reps = replicate_differences(a, b, "image", True, False)
    assert len(reps.difference) == 4 and reps.difference.iloc[-1] == -np.inf
    assert np.isfinite(reps.difference.iloc[:3]).all() and reps.undefined == (2, 0)


def test_an_undefined_held_out_output_fails_the_runs_eval_scores_not_its_search_or_time():
    """A searched expression undefined on one held-out image (eval_undefined > 0): its held-out relMSE is
    its worst outcome, but its search fitness and its running time were measured all the same."""
    runs = pd.DataFrame(
        {
            "params.seed": ["0", "0"],
            "params.model.name": ["a", "b"],
            "metrics.eval_relmse": [0.1, 0.2],
            "metrics.search_seconds": [10.0, 60.0],
            "metrics.eval_undefined": [0.1, 0.0],
        }
    )
    for metric, failed in (("eval_relmse", [True, False]), ("search_seconds", [False, False])):
        claim = replace(_claim("x", "{model.name: a}", "{model.name: b}", metric), per="run")
        scores, _ = item_scores(claim, runs)
        assert list(scores["failed"]) == failed, metric
        assert list(scores["value"]) == list(runs[f"metrics.{metric}"])


def _search_store(tmp_path, normal, rival):
    """A `gp_population` study at cpu: per seed, at the profile's population (16), one search whose error
    fell from 1.0 at generation 0 to 0.5 + 0.01 x seed by generation 10 and to 0.4 + ... by 20, with the
    normal's and its top rival's occurrences in the best expression; and one at population 64 whose
    numbers would change every result if the claims read it."""
    client = MlflowClient()
    exp = client.create_experiment("nrbench-filter_search", artifact_location=(tmp_path / "art").as_uri())
    for seed in range(6):
        for population in (16, 64):
            other = population != 16
            params = {
                "report.name": "sweeps/gp_population",
                "task.name": "filter_search",
                "model.name": "gp_filter",
                "model.learned": "False",
                "task.search.population": population,
                "seed": seed,
            }
            metrics = {
                "search_best_initial": 1.0,
                "search_best_midway": 0.5 + 0.01 * seed,
                "search_best_so_far": 0.9 if other else 0.4 + 0.01 * seed,
                "search_feature_normal": 0.0 if other else float(normal[seed]),
                "search_feature_top_rival": 9.0 if other else float(rival[seed]),
            }
            job = f"task.search.population={population} seed={seed} +sweep=gp_population profile=cpu"
            log_run(client, exp, tmp_path, params, {**CPU, "nrbench.hydra_job": job}, metrics)


@pytest.mark.parametrize(
    ("normal", "rival", "status"),
    [([4, 3, 4, 5, 3, 4], [2, 2, 2, 2, 2, 2], REPRODUCED), ([2] * 6, [2] * 6, NOT_DISTINGUISHABLE)],
)
def test_the_gp_generation_and_feature_claims_read_two_measures_of_the_same_runs(
    tmp_path, normal, rival, status
):
    """The claims file's own GP claims at cpu that pair two run metrics of each search (`b_metric`) on a
    hand-made store: the error fell in every run (both halves); the normal leads its rival on every seed,
    or ties (the seed expression's two normals against its two depths)."""
    from src.report.claims import load_claims

    previous = mlflow.get_tracking_uri()
    mlflow.set_tracking_uri(f"sqlite:///{tmp_path}/mlflow.db")
    try:
        _search_store(tmp_path, normal, rival)
        claims = {c.id: c for c in load_claims(Path(CONF_DIR) / "claims.yaml")}
        settings = _settings(tmp_path)
        rows = {
            name: evaluate_claim(claims[name], settings)
            for name in (
                "gp_error_falls_with_generations_cpu",
                "gp_error_still_falls_in_second_half_cpu",
                "gp_normal_is_the_most_used_feature_cpu",
            )
        }
    finally:
        mlflow.set_tracking_uri(previous)
    falls = rows["gp_error_falls_with_generations_cpu"]
    assert falls.verdict.status == REPRODUCED and falls.replicates.unit == "seeds"
    assert falls.verdict.items == 6  # one replicate per seed: its run at the claim's population only
    # 1.0 -> 0.4 + 0.01 s: the mean log ratio per seed, then the Hodges-Lehmann estimate of the six
    expected = np.log(np.array([1.0] * 6) / (0.4 + 0.01 * np.arange(6)))
    assert np.sort(
        -rows["gp_error_falls_with_generations_cpu"].replicates.difference.to_numpy()
    ) == pytest.approx(np.sort(expected))
    half = rows["gp_error_still_falls_in_second_half_cpu"]
    assert half.verdict.status == REPRODUCED
    assert -half.replicates.difference.to_numpy() == pytest.approx(
        np.log((0.5 + 0.01 * np.arange(6)) / (0.4 + 0.01 * np.arange(6)))
    )
    feature = rows["gp_normal_is_the_most_used_feature_cpu"]
    assert feature.verdict.status == status, feature.verdict.numbers
    assert feature.replicates.difference.to_numpy() == pytest.approx(np.array(normal) - np.array(rival))


def test_a_family_adjustment_that_lifts_p_over_alpha_changes_the_status(probe_store, tmp_path):
    """Benjamini-Hochberg over a family: a claim significant alone (p = 2/2^6 = 0.031) beside one with
    p = 0.5 gets p_adjusted = min(2 x 0.031, 0.5) = 0.0625 > 0.05, and its status is judged again on that
    p; alone in its family its p and status stay. (A re-judged status must replace the row's, not only its
    printed p.)"""
    from dataclasses import replace

    from src.report.ledger import adjust_families

    claim = _claim(
        "budgets", "{model.name: kpcn}", "{model.name: dpcn}", extra=", ratio: {task.train.epochs: 0.5}"
    )
    row = evaluate_claim(claim, _settings(tmp_path))
    assert row.verdict.status == REPRODUCED and row.verdict.p_value == pytest.approx(2 / 64)
    other = replace(row, verdict=replace(row.verdict, p_value=0.5))  # a second test of the same study
    alone, pair = adjust_families([row], 0.05), adjust_families([row, other], 0.05)
    assert alone[0].verdict.status == REPRODUCED and alone[0].p_adjusted == pytest.approx(2 / 64)
    assert alone[0].family == "study budgets at cpu (1 tests)"
    assert pair[0].p_adjusted == pytest.approx(4 / 64) and pair[0].family == "study budgets at cpu (2 tests)"
    assert pair[0].verdict.status != REPRODUCED  # 0.0625 > alpha: no longer a finding
    assert pair[0].verdict.p_value == pytest.approx(2 / 64)  # the raw p is kept beside the adjusted one
    assert adjust_families([row, other], 0.1)[0].verdict.status == REPRODUCED  # the level that arrives


def test_the_ledger_settings_read_every_ledger_key_away_from_its_default():
    """`settings_from`: each `ledger.*` value arrives as set (not the dataclass default), the profiles are
    the conf folder's beside the claims file, and the budget and recipe keys are read from that folder."""
    from omegaconf import OmegaConf

    from src.report.ledger import settings_from
    from src.report.matched_arms import model_keys

    conf = Path(CONF_DIR)
    cfg = OmegaConf.create(
        {
            "ledger": {
                "alpha": 0.1,
                "equivalent_commits": [["aaaa111", "bbbb222"], [123, "cccc333"]],
                "budget_shown": ["task.train.epochs", "seed"],
                "profile_order": ["paper", "smoke"],
            }
        }
    )
    settings = settings_from(cfg, conf / "claims.yaml")
    assert settings.alpha == 0.1
    assert settings.equivalent_commits == (("aaaa111", "bbbb222"), ("123", "cccc333"))  # as text
    assert settings.budget_shown == ("task.train.epochs", "seed")
    assert settings.profile_order == ("paper", "smoke")
    assert settings.all_profiles == ("bako", "cpu", "paper", "smoke", "thesis")  # conf/profile/*.yaml
    assert settings.budget_keys == profile_keys(conf) and "task.train.epochs" in settings.budget_keys
    assert settings.model_keys == model_keys(conf) and settings.model_keys
    bare = settings_from(OmegaConf.create({"ledger": {"alpha": 0.05}}), conf / "claims.yaml")
    assert bare.equivalent_commits == () and bare.budget_shown == ()
    assert bare.profile_order == ("smoke", "cpu", "paper", "thesis", "bako")  # the default order


def test_an_agreement_claim_matches_each_case_among_its_own_runs_only(probe_store, tmp_path):
    """Each published case is checked against its own value, so its runs must match among themselves
    but not with another case's: kpcn's and dpcn's runs of the `commits` study were made at two commits
    (a better claim between them is confounded, above), and still agree with their published numbers."""

    def agreement(study, cases):
        rule = f"{{kind: agreement, tolerance: 0.1, tolerance_source: ours, published: [{cases}]}}"
        return _rule_claim(study, rule)

    kpcn, dpcn = "{arm: {model.name: kpcn}, value: 35.75}", "{arm: {model.name: dpcn}, value: 34.75}"
    row = evaluate_claim(agreement("commits", f"{kpcn}, {dpcn}"), _settings(tmp_path))
    assert row.verdict.status == REPRODUCED, row.verdict.numbers
    # a case whose own runs were made at two commits is confounded, and named
    split = agreement("commits_split", kpcn)
    mixed = evaluate_claim(split, _settings(tmp_path))
    assert mixed.verdict.status == CONFOUNDED
    assert (
        mixed.verdict.numbers
        == "the compared runs are not matched: kpcn: code commit differs (aaaa111, bbbb222)"
    )
    same_code = _settings(tmp_path, equivalent_commits=(("aaaa111", "bbbb222"),))
    assert evaluate_claim(split, same_code).verdict.status == REPRODUCED


def test_a_second_metric_of_the_same_runs_is_matched_with_the_equivalent_commits(probe_store, tmp_path):
    """A claim pairing two metrics of one arm's runs (`b_metric`) checks those runs as one set: kpcn's
    seeds of `commits_split` were made at two commits, which `ledger.equivalent_commits` may declare the
    same code."""
    claim = _claim(
        "commits_split", "{model.name: kpcn}", "{model.name: kpcn}", extra=", b_metric: relmse_ratio"
    )
    split = evaluate_claim(claim, _settings(tmp_path))
    assert (
        split.verdict.status == CONFOUNDED
        and "code commit differs (aaaa111, bbbb222)" in split.verdict.numbers
    )
    same_code = _settings(tmp_path, equivalent_commits=(("aaaa111", "bbbb222"),))
    assert evaluate_claim(claim, same_code).verdict.status == REPRODUCED


def test_a_run_that_logged_no_undefined_share_is_defined():
    """Runs of older code logged no `eval_undefined`: beside runs that did, theirs is empty, and counts
    as defined (a run with an undefined share > 0 fails, whether or not its score was logged)."""
    claim = replace(_claim("any", "{model.name: a}", "{model.name: b}", metric="eval_psnr"), per="run")
    runs = pd.DataFrame(
        {
            "params.model.name": ["a", "a", "a", "b"],
            "metrics.eval_psnr": [30.0, 31.0, np.nan, 29.0],
            "metrics.eval_undefined": [0.0, np.nan, 0.5, 0.0],
        }
    )
    scores, prefix = item_scores(claim, runs)
    assert prefix == "params." and list(scores["failed"]) == [False, False, True, False]
    assert list(scores["value"].fillna(-1.0)) == [30.0, 31.0, -1.0, 29.0]
