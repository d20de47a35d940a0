"""The reproduction ledger: the status rules (src/report/verdicts.py) on numbers whose answer is known, the
claims file's reader (src/report/claims.py), and the ledger built from fixture MLflow runs of a study and
a benchmark (src/report/ledger.py), through `python -m src.run stage=ledger` for its errors."""

import math
import subprocess
import sys
import textwrap

import mlflow
import numpy as np
import pandas as pd
import pytest
from mlflow.entities import Metric, Param
from mlflow.tracking import MlflowClient
from omegaconf import OmegaConf

from src.errors import ConfigError
from src.report.claims import load_claims
from src.report.ledger import arm_values, build_ledger, matching
from src.report.verdicts import (
    DIRECTION_ONLY,
    NOT_DISTINGUISHABLE,
    NOT_REPRODUCED,
    NOT_RUN,
    REPRODUCED,
    agreement_verdict,
    better_verdict,
    comparable_verdict,
    min_items,
)
from tests.conftest import ROOT, one_line_cli_error, one_line_error

NAMES = ("a", "b")


def _items(values):
    return pd.Series(values, index=[f"item{i}" for i in range(len(values))], dtype=float)


# --- the status rules ----------------------------------------------------------------------------------


def test_min_items_is_the_first_count_whose_smallest_signed_rank_p_is_below_alpha():
    for alpha in (0.05, 0.01, 0.0625, 0.2):
        n = min_items(alpha)
        assert 2 / 2**n < alpha <= 2 / 2 ** (n - 1), alpha
    assert min_items(0.05) == 6


def test_better_separates_reproduced_direction_only_reversed_and_inside_the_spread():
    b = _items([20.0, 21.0, 22.0, 23.0, 24.0, 25.0, 26.0, 27.0])
    a = b + _items([1.0, 1.2, 0.8, 1.1, 0.9, 1.0, 1.3, 0.7])  # +1 dB on every item
    assert better_verdict(a, b, NAMES, True, False, 0.0, 0.05).status == REPRODUCED
    assert better_verdict(a, b, NAMES, True, False, 0.5, 0.05).status == REPRODUCED
    short = better_verdict(a, b, NAMES, True, False, 2.0, 0.05)  # the source claims 2 dB
    assert short.status == DIRECTION_ONLY and "published size 2" in short.numbers
    assert better_verdict(b, a, NAMES, True, False, 0.0, 0.05).status == NOT_REPRODUCED
    # Lower is better (an error): a's higher values are worse.
    assert better_verdict(a, b, NAMES, False, False, 0.0, 0.05).status == NOT_REPRODUCED
    noise = b + _items([0.5, -0.4, 0.3, -0.6, 0.2, -0.1, 0.4, -0.3])
    assert better_verdict(noise, b, NAMES, True, False, 0.0, 0.05).status == NOT_DISTINGUISHABLE
    verdict = better_verdict(a, b, NAMES, True, False, 0.0, 0.05)
    assert "+1 over 8 paired items (8 favour a, 0 b" in verdict.numbers and verdict.items == 8


def test_better_pairs_items_by_name_not_by_position():
    b = _items([10.0, 20.0, 30.0, 40.0, 50.0, 60.0])
    a = (b + 1.0).iloc[::-1]  # the same items, listed in the other order
    verdict = better_verdict(a, b, NAMES, True, False, 0.0, 0.05)
    assert verdict.status == REPRODUCED and "+1 over 6" in verdict.numbers


def test_five_items_can_never_show_a_difference_and_the_verdict_says_so():
    b = _items([1.0, 2.0, 3.0, 4.0, 5.0])
    verdict = better_verdict(b + 5, b, NAMES, True, False, 0.0, 0.05)
    assert verdict.status == NOT_DISTINGUISHABLE and "needs 6 or more" in verdict.numbers


def test_better_on_a_log_scale_compares_factors_with_the_published_size():
    kpcn = _items([1.0, 1.2, 0.9, 1.1, 1.05, 0.95, 1.0])  # seconds per round
    unet = kpcn / 12.0
    fast = better_verdict(unet, kpcn, ("unet", "kpcn"), False, True, 10.0, 0.05)
    assert fast.status == REPRODUCED and "factor 12" in fast.numbers
    slower = better_verdict(kpcn / 5.0, kpcn, ("unet", "kpcn"), False, True, 10.0, 0.05)
    assert slower.status == DIRECTION_ONLY and "factor 5" in slower.numbers


def test_one_common_item_is_not_run_rather_than_a_test():
    verdict = better_verdict(_items([1.0]), _items([0.0, 2.0]), NAMES, True, False, 0.0, 0.05)
    assert verdict.status == NOT_RUN


def test_comparable_uses_the_t_interval_of_the_paired_mean():
    b = _items([20.0, 21.0, 22.0, 23.0])
    a = b + _items([0.1, -0.1, 0.1, -0.1])  # mean 0, sd 0.11547: the 95 % half-width is 3.1824 * 0.057735
    half = 3.182446 * 0.1154701 / 2
    assert comparable_verdict(a, b, NAMES, False, half + 0.01).status == REPRODUCED
    assert comparable_verdict(a, b, NAMES, False, half - 0.01).status == NOT_DISTINGUISHABLE
    far = comparable_verdict(b + 1.0 + (a - b), b, NAMES, False, 0.5)
    assert far.status == NOT_REPRODUCED and f"[{1 - half:+.4g}, {1 + half:+.4g}]" in far.numbers


def test_agreement_needs_every_case_that_ran_within_the_tolerance():
    cases = [("nerf, lego", _items([31.5, 31.7]), 31.6), ("mipnerf, lego", _items([33.0, 33.2]), 33.0)]
    assert agreement_verdict(cases, 0.2).status == REPRODUCED
    off = agreement_verdict([*cases, ("refnerf, lego", _items([30.0]), 33.0)], 0.2)
    assert off.status == NOT_REPRODUCED and off.numbers.startswith("2 of 3 case(s) within")
    partly = agreement_verdict([*cases, ("refnerf, lego", None, 33.0)], 0.2)
    assert partly.status == REPRODUCED and "1 of 3 not run" in partly.numbers
    assert agreement_verdict([("x", None, 1.0)], 0.2).status == NOT_RUN


# --- the claims file -----------------------------------------------------------------------------------

CLAIM = """
  - id: {id}
    source: {{document: Bunjevac 2019, section: "6.2", where: Table 6.3}}
    statement: KPCN beats DPCN.
    profiles: [paper, cpu]
    runs: {{study: denoisers, experiment: nrbench-denoise}}
    metric: psnr
    per: image
    higher: true
    rule: {{kind: better, a: {{model.name: kpcn}}, b: {{model.name: dpcn}}}}
"""


AGREEMENT_B_METRIC = (
    "kind: agreement, tolerance: 1, published: [{arm: {model.name: dpcn}, value: 1}], b_metric: m"
)


def _claims_file(tmp_path, text):
    path = tmp_path / "claims.yaml"
    path.write_text(text)
    return path


def test_the_claims_reader_keeps_what_the_file_says(tmp_path):
    (claim,) = load_claims(_claims_file(tmp_path, "claims:" + CLAIM.format(id="kpcn_dpcn")))
    assert claim.citation == "Bunjevac 2019, Sec. 6.2, Table 6.3"
    assert (claim.sources, claim.profiles) == ((("study", "denoisers"),), ("paper", "cpu"))
    assert claim.rule.a == {"model.name": "kpcn"} and claim.rule.size == 0.0
    assert claim.command("cpu") == "python -m src.run -m +sweep=denoisers profile=cpu"


@pytest.mark.parametrize(
    "edit, needles",
    [
        (lambda t: t + CLAIM.format(id="kpcn_dpcn"), ["'kpcn_dpcn' appears twice"]),
        (lambda t: t.replace("kind: better", "kind: bigger"), ["claims.kpcn_dpcn.rule.kind", "bigger"]),
        (
            lambda t: t.replace("study: denoisers", "study: denoisers, bench: denoise"),
            ["runs", "a bench alone"],
        ),
        (lambda t: t.replace("per: image", "per: round"), ["claims.kpcn_dpcn.per", "round"]),
        (lambda t: t.replace("experiment: nrbench-denoise", "where: {}"), ["runs.experiment"]),
        (lambda t: t.replace("b: {model.name: dpcn}", "b: {model.name: kpcn}"), ["two different"]),
        (
            lambda t: t.replace(
                "kind: better, a: {model.name: kpcn}, b: {model.name: dpcn}", AGREEMENT_B_METRIC
            ),
            ["rule.b_metric", "agreement"],
        ),
        (lambda t: t.replace("profiles: [paper, cpu]", "profiles: cpu"), ["profiles"]),
        (
            lambda t: t.replace("b: {model.name: dpcn}}", "b: {model.name: dpcn}, sise: 1}"),
            ["rule", "'sise'"],
        ),
        (lambda t: t.replace("higher: true", "higher: true\n    metirc: psnr"), ["kpcn_dpcn", "'metirc'"]),
    ],
)
def test_a_malformed_claim_is_one_line_naming_its_key(tmp_path, edit, needles):
    path = _claims_file(tmp_path, edit("claims:" + CLAIM.format(id="kpcn_dpcn")))
    with pytest.raises(ConfigError) as excinfo:
        load_claims(path)
    one_line_error(excinfo, *needles)


def test_param_values_match_by_value_not_by_spelling():
    runs = pd.DataFrame({"params.w": ["0.0", "0.5", "True", "kpcn"]})
    assert list(matching(runs, {"w": "0"})) == [True, False, False, False]
    assert list(matching(runs, {"w": "true"})) == [False, False, True, False]
    assert not matching(runs, {"absent": "1"}).any()


def test_an_arm_scored_twice_on_one_item_counts_its_mean_once():
    scores = pd.DataFrame(
        {
            "params.model.name": ["kpcn", "kpcn", "kpcn", "dpcn"],
            "params.seed": ["0", "0", "1", "0"],
            "value": [1.0, 3.0, 5.0, 7.0],
        }
    )
    values = arm_values(scores, {"model.name": "kpcn"}, "params.", ["params.seed", "scene"])
    assert values.to_dict() == {("0", "-"): 2.0, ("1", "-"): 5.0}


# --- the ledger from logged runs -----------------------------------------------------------------------

STUDY = "toy_study"


def _log(client, experiment_id, tmp, params, tags, metrics=None, artifact=None):
    run_id = client.create_run(experiment_id, tags=tags).info.run_id
    client.log_batch(
        run_id,
        params=[Param(k, str(v)) for k, v in params.items()],
        metrics=[Metric(k, v, 0, 0) for k, v in (metrics or {}).items()],
    )
    if artifact is not None:
        folder, frame = artifact
        path = tmp / run_id / folder.rsplit("/", 1)[-1]
        path.parent.mkdir(parents=True)
        frame.to_csv(path, index=False)
        client.log_artifact(run_id, str(path), folder.rsplit("/", 1)[0])
    client.set_terminated(run_id, "FINISHED")
    return run_id


def _images(psnr):
    return pd.DataFrame({"scene": ["s0", "s1"], "spp": [4, 4], "psnr": psnr, "relmse_ratio": [0.5, 0.5]})


@pytest.fixture(scope="module")
def ledger_store(tmp_path_factory):
    """A study (`kpcn` 1 dB above `dpcn` on 2 images x 4 seeds, an older kpcn rerun 10 dB below that the
    ledger must not count), a study run at smoke only, and benchmarks with 7 rounds: at paper size in fp32
    an older run (U-Net 5x faster than KPCN) and the newest (12x faster, 1.5x slower than OIDN), then a
    bf16 one (3x), and a newer one at cpu size (only 2x faster)."""
    tmp = tmp_path_factory.mktemp("ledger_store")
    previous = mlflow.get_tracking_uri()
    uri = f"sqlite:///{tmp}/mlflow.db"
    mlflow.set_tracking_uri(uri)
    client = MlflowClient()
    denoise = client.create_experiment("nrbench-denoise", artifact_location=(tmp / "art").as_uri())
    bench = client.create_experiment("nrbench-bench", artifact_location=(tmp / "art_bench").as_uri())
    cpu = {"nrbench.profile": "cpu", "nrbench.git_commit": "abc1234def", "nrbench.data_fingerprint": "f00d"}
    study = {"report.name": f"sweeps/{STUDY}"}
    rng = np.random.default_rng(0)
    for seed in range(4):
        base = 25 + rng.normal(0, 1, 2)
        _log(
            client,
            denoise,
            tmp,
            {**study, "model.name": "kpcn", "seed": seed},
            cpu,
            artifact=("eval/per_image.csv", _images(base - 9)),
        )  # the older run: replaced by the next
        _log(
            client,
            denoise,
            tmp,
            {**study, "model.name": "kpcn", "seed": seed},
            cpu,
            {"eval_psnr": float(np.mean(base + 1))},
            # with a baseline scored beside it on the same images, 0.4 dB below it
            ("eval/per_image.csv", _images(base + 1).assign(baseline_psnr=base + 0.6)),
        )
        _log(
            client,
            denoise,
            tmp,
            {**study, "model.name": "dpcn", "seed": seed},
            cpu,
            {"eval_psnr": float(np.mean(base))},
            ("eval/per_image.csv", _images(base)),
        )
    # The DVC pipeline's runs: one seed per model, 6 held-out images, kpcn 0.5 dB above dpcn on each.
    pipeline = {**cpu, "nrbench.group": "dvc"}
    six = pd.DataFrame({"scene": [f"p{i}" for i in range(6)], "spp": 4, "relmse_ratio": 0.5})
    for model, offset in (("kpcn", 0.5), ("dpcn", 0.0)):
        scores = six.assign(psnr=[24.0 + i + offset for i in range(6)])
        _log(
            client,
            denoise,
            tmp,
            {"report.name": "denoise", "model.name": model, "seed": 0},
            pipeline,
            artifact=("eval/per_image.csv", scores),
        )
    # The radiance fields' pipeline: one run per model, scored per test view (`view`, no scene or spp):
    # refnerf 0.3 dB above mipnerf on each of 6 views, which must pair as 6 items, not one.
    nerf = client.create_experiment("nrbench-nerf", artifact_location=(tmp / "art_nerf").as_uri())
    views = pd.DataFrame({"view": [f"tabletop-r_{i}" for i in range(6)]})
    for model, offset in (("refnerf", 0.3), ("mipnerf", 0.0)):
        scores = views.assign(psnr=[23.0 + 0.2 * i + offset for i in range(6)])
        params = {"report.name": "nerf", "model.name": model, "seed": 0, "task.scene": "tabletop"}
        _log(client, nerf, tmp, params, pipeline, artifact=("eval/per_image.csv", scores))
    # A third model of the study, which no claim compares: its run is not one of a claim's runs.
    _log(
        client,
        denoise,
        tmp,
        {**study, "model.name": "resnet", "seed": 0},
        {**cpu, "nrbench.git_commit": "0ther"},
        {"eval_psnr": 20.0},
        ("eval/per_image.csv", _images([20.0, 20.0])),
    )
    smoke = {**cpu, "nrbench.profile": "smoke"}
    for model in ("kpcn", "dpcn"):
        _log(
            client,
            denoise,
            tmp,
            {"report.name": "sweeps/smoke_only", "model.name": model, "seed": 0},
            smoke,
            artifact=("eval/per_image.csv", _images([20.0, 21.0])),
        )
    times = {"kpcn": 1.2, "unet_kpcn": 0.1, "oidn": 0.1 / 1.5}
    rounds = pd.DataFrame(
        [{"round": r, "model": m, "seconds": t * (1 + 0.01 * r)} for r in range(7) for m, t in times.items()]
    )
    paper = {**cpu, "nrbench.profile": "paper"}
    older = rounds.assign(seconds=np.where(rounds["model"] == "kpcn", 0.5, rounds["seconds"]))  # 5x
    fp32 = {"bench": "denoise", "autocast": "none"}
    _log(client, bench, tmp, fp32, paper, artifact=("bench/rounds.csv", older))
    _log(client, bench, tmp, fp32, paper, artifact=("bench/rounds.csv", rounds))
    # The newest paper run is in bf16, which the claim's `where` leaves out: the fp32 run before it counts.
    bf16 = rounds.assign(seconds=np.where(rounds["model"] == "kpcn", 0.3, rounds["seconds"]))
    _log(client, bench, tmp, {**fp32, "autocast": "bf16"}, paper, artifact=("bench/rounds.csv", bf16))
    # A newer bench run at the cpu profile, where the U-Net is only 2x faster: the claims that list paper
    # first must still read the paper run.
    cpu_rounds = rounds.assign(seconds=np.where(rounds["model"] == "kpcn", 0.2, rounds["seconds"]))
    _log(client, bench, tmp, {"bench": "denoise"}, cpu, artifact=("bench/rounds.csv", cpu_rounds))
    yield {"tmp": tmp, "uri": uri}
    mlflow.set_tracking_uri(previous)


LEDGER_CLAIMS = textwrap.dedent(
    f"""
    claims:
      - id: kpcn_beats_dpcn
        source: {{document: Doc A, section: "1"}}
        statement: KPCN beats DPCN.
        profiles: [paper, cpu]
        runs: {{study: {STUDY}, experiment: nrbench-denoise}}
        metric: psnr
        per: image
        higher: true
        rule: {{kind: better, a: {{model.name: kpcn}}, b: {{model.name: dpcn}}, size: 0.5}}
      - id: kpcn_beats_dpcn_by_3db
        source: {{document: Doc A, section: "1"}}
        statement: KPCN beats DPCN by 3 dB.
        profiles: [cpu]
        runs: {{study: {STUDY}, experiment: nrbench-denoise}}
        metric: psnr
        per: image
        higher: true
        rule: {{kind: better, a: {{model.name: kpcn}}, b: {{model.name: dpcn}}, size: 3}}
      - id: pipeline_fallback
        source: {{document: Doc A, section: "1"}}
        statement: KPCN beats DPCN; its study never ran, the pipeline did.
        profiles: [cpu]
        runs: {{study: never_run, pipeline: denoise, experiment: nrbench-denoise}}
        metric: psnr
        per: image
        higher: true
        rule: {{kind: better, a: {{model.name: kpcn}}, b: {{model.name: dpcn}}}}
      - id: study_first
        source: {{document: Doc A, section: "1"}}
        statement: KPCN beats DPCN; both the study and the pipeline ran.
        profiles: [cpu]
        runs: {{study: {STUDY}, pipeline: denoise, experiment: nrbench-denoise}}
        metric: psnr
        per: image
        higher: true
        rule: {{kind: better, a: {{model.name: kpcn}}, b: {{model.name: dpcn}}, size: 0.8}}
      - id: per_seed
        source: {{document: Doc A, section: "1"}}
        statement: KPCN beats DPCN, per run.
        profiles: [cpu]
        runs: {{study: {STUDY}, experiment: nrbench-denoise}}
        metric: eval_psnr
        per: run
        higher: true
        rule: {{kind: better, a: {{model.name: kpcn}}, b: {{model.name: dpcn}}}}
      - id: beats_its_baseline
        source: {{document: Doc A, section: "1"}}
        statement: KPCN beats the baseline its runs score beside it.
        profiles: [cpu]
        runs: {{study: {STUDY}, experiment: nrbench-denoise}}
        metric: psnr
        per: image
        higher: true
        rule: {{kind: better, a: {{model.name: kpcn}}, b: {{model.name: kpcn}}, b_metric: baseline_psnr}}
      - id: no_baseline_scored
        source: {{document: Doc A, section: "1"}}
        statement: DPCN's runs score no baseline.
        profiles: [cpu]
        runs: {{study: {STUDY}, experiment: nrbench-denoise}}
        metric: psnr
        per: image
        higher: true
        rule: {{kind: better, a: {{model.name: dpcn}}, b: {{model.name: dpcn}}, b_metric: baseline_psnr}}
      - id: smoke_only
        source: {{document: Doc A, section: "2"}}
        statement: Only ever run at smoke.
        profiles: [cpu]
        runs: {{study: smoke_only, experiment: nrbench-denoise}}
        metric: psnr
        per: image
        higher: true
        rule: {{kind: better, a: {{model.name: kpcn}}, b: {{model.name: dpcn}}}}
      - id: unet_10x
        source: {{document: Doc B, section: "4"}}
        statement: The U-Net is at least 10x faster than KPCN.
        profiles: [paper, cpu]
        needs: gpu
        runs: {{bench: denoise, experiment: nrbench-bench, where: {{autocast: none}}}}
        metric: seconds
        per: round
        higher: false
        log: true
        rule: {{kind: better, a: {{model: unet_kpcn}}, b: {{model: kpcn}}, size: 10}}
      - id: unet_vs_oidn
        source: {{document: Doc B, section: "4"}}
        statement: The U-Net is within 2x of OIDN.
        profiles: [paper]
        runs: {{bench: denoise, experiment: nrbench-bench}}
        metric: seconds
        per: round
        higher: false
        log: true
        rule: {{kind: comparable, a: {{model: unet_kpcn}}, b: {{model: oidn}}, tolerance: {math.log(2)}}}
      - id: published
        source: {{document: Doc C, section: "6", where: Table 6.1}}
        statement: DPCN reaches the published PSNR.
        profiles: [cpu]
        runs: {{study: {STUDY}, experiment: nrbench-denoise}}
        metric: eval_psnr
        per: run
        higher: true
        rule: {{kind: agreement, tolerance: 5, published: [{{arm: {{model.name: dpcn}}, value: 25.0}}]}}
      - id: nerf_views
        source: {{document: Doc C, section: "6"}}
        statement: Ref-NeRF beats mip-NeRF, per test view.
        profiles: [cpu]
        runs: {{pipeline: nerf, experiment: nrbench-nerf, where: {{task.scene: tabletop}}}}
        metric: psnr
        per: image
        higher: true
        rule: {{kind: better, a: {{model.name: refnerf}}, b: {{model.name: mipnerf}}}}
      - id: needs_scenes
        source: {{document: Doc C, section: "6"}}
        statement: Needs the user's scenes.
        profiles: [thesis]
        needs: user_data
        runs: {{study: nerf_thesis, experiment: nrbench-nerf}}
        metric: psnr
        per: image
        higher: true
        rule: {{kind: agreement, tolerance: 0.2, published: [{{arm: {{model.name: nerf}}, value: 31.0}}]}}
    """
)


def _ledger_cfg(store, tmp_path, claims_text=LEDGER_CLAIMS):
    conf = tmp_path / "conf"
    (conf / "profile").mkdir(parents=True)
    for profile in ("smoke", "cpu", "paper", "thesis"):
        (conf / "profile" / f"{profile}.yaml").write_text("{}\n")
    (conf / "claims.yaml").write_text(claims_text)
    return OmegaConf.create(
        {
            "ledger": {
                "claims": str(conf / "claims.yaml"),
                "out_dir": str(tmp_path / "reports"),
                "alpha": 0.05,
            },
            "tracking": {"uri": store["uri"]},
        }
    )


def test_the_ledger_computes_each_status_from_the_runs(ledger_store, tmp_path):
    summary = build_ledger(_ledger_cfg(ledger_store, tmp_path))
    assert summary["statuses"] == {
        "kpcn_beats_dpcn": REPRODUCED,  # +1 dB on all 8 (seed, image) items, older reruns left out
        "kpcn_beats_dpcn_by_3db": DIRECTION_ONLY,
        "pipeline_fallback": REPRODUCED,  # +0.5 dB on the pipeline's 6 images
        "study_first": REPRODUCED,  # the study's +1 dB: the pipeline's 0.5 would be direction only
        "per_seed": NOT_DISTINGUISHABLE,  # 4 seeds: a signed-rank test cannot show it
        "beats_its_baseline": REPRODUCED,  # +0.4 dB over its own runs' baseline on all 8 items
        "no_baseline_scored": NOT_RUN,
        "smoke_only": NOT_RUN,
        "unet_10x": REPRODUCED,
        "unet_vs_oidn": REPRODUCED,
        "published": REPRODUCED,
        "nerf_views": REPRODUCED,  # +0.3 dB on each of 6 views: 6 items, not 1
        "needs_scenes": NOT_RUN,
    }
    ledger = pd.read_csv(summary["paths"]["csv"]).set_index("claim")
    kpcn = ledger.loc["kpcn_beats_dpcn"]
    assert kpcn["profile"] == "cpu" and kpcn["runs"] == 8  # the newest run per model and seed
    assert "kpcn - dpcn = +1 over 8 paired items (8 favour kpcn, 0 dpcn" in kpcn["numbers"]
    assert kpcn["commits"] == "abc1234def" and kpcn["data"] == "f00d" and kpcn["source"] == "Doc A, Sec. 1"
    assert (
        ledger.loc["pipeline_fallback", "from"] == "pipeline" and ledger.loc["pipeline_fallback", "runs"] == 2
    )
    assert "+0.5 over 6 paired items" in ledger.loc["pipeline_fallback", "numbers"]
    assert ledger.loc["study_first", "from"] == f"study {STUDY}" and kpcn["from"] == f"study {STUDY}"
    assert "factor 12" in ledger.loc["unet_10x", "numbers"] and ledger.loc["unet_10x", "profile"] == "paper"
    assert "needs 6 or more" in ledger.loc["per_seed", "numbers"]
    smoke = ledger.loc["smoke_only", "numbers"]
    assert "runs at smoke only" in smoke and "python -m src.run -m +sweep=smoke_only profile=cpu" in smoke
    assert "+0.3 over 6 paired items" in ledger.loc["nerf_views", "numbers"]
    assert (
        "kpcn - kpcn (baseline_psnr) = +0.4 over 8 paired items"
        in ledger.loc["beats_its_baseline", "numbers"]
    )
    assert "no psnr scores for arm dpcn (baseline_psnr)" in ledger.loc["no_baseline_scored", "numbers"]
    scenes = ledger.loc["needs_scenes", "numbers"]
    assert scenes.startswith("needs the user's data") and "+sweep=nerf_thesis profile=thesis" in scenes
    md = (tmp_path / "reports" / "ledger.md").read_text()
    assert "**8 reproduced, 1 direction only, 1 not distinguishable, 3 not run**" in md
    assert md.count("\n| ") == 1 + 13  # the header and one row per claim
    html = (tmp_path / "reports" / "ledger.html").read_text()
    assert html.count("<tr>") == 1 + 13 and "#d4edda" in html


def test_a_slower_unet_is_not_reproduced(ledger_store, tmp_path):
    claims = LEDGER_CLAIMS.replace(
        "a: {model: unet_kpcn}, b: {model: kpcn}", "a: {model: kpcn}, b: {model: unet_kpcn}"
    )
    assert build_ledger(_ledger_cfg(ledger_store, tmp_path, claims))["statuses"]["unet_10x"] == NOT_REPRODUCED


def test_the_ledger_stage_refuses_a_bad_claims_file_in_one_line(tmp_path):
    claims = _claims_file(tmp_path, "claims:" + CLAIM.format(id="x").replace("per: image", "per: pixel"))
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "src.run",
            "stage=ledger",
            f"ledger.claims={claims}",
            f"ledger.out_dir={tmp_path / 'out'}",
            f"tracking.uri=sqlite:///{tmp_path}/m.db",
            f"hydra.run.dir={tmp_path / 'h'}",
        ],
        cwd=ROOT,
        capture_output=True,
        text=True,
        check=False,
    )
    one_line_cli_error(result, "claims.x.per", "pixel")
    assert not (tmp_path / "out").exists()
