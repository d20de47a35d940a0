"""conf/claims.yaml, the reproduction ledger's claims: every claim has the schema's keys with allowed values,
and names runs, arms, metrics and experiments the harness really produces, so that a typo (a misspelt
study or model, a boolean written `true` where MLflow logs `True`, a metric the runs never log) fails here
rather than leaving a claim silently "not run" in the ledger.

Every claim also says what kind of statement it is (`category`: finding, reading, target, setup), quotes
the seed sentence a finding or reading rests on (with an English translation unless the seed is in
English), and names where each comparable or agreement tolerance comes from (`rule.tolerance_source`). The
quotes are checked for presence here, not against the seed texts, which CI does not have.

The arms are checked against the study's jobs: each study is composed as `python -m src.run -m
+sweep=<study> profile=<p>` would compose it (tests/test_sweeps.py's helpers), each combination of its
swept values (seeds aside) becomes a job config, and every arm must equal, as MLflow logs it
(`src.tracking.run_config.flatten_config`), the params of at least one job at every profile it lists.
"""

from __future__ import annotations

import copy
import itertools
import re
from functools import cache
from pathlib import Path

import pytest
import yaml
from omegaconf import DictConfig, OmegaConf

from src.bench.denoise import AUTOCAST_DTYPES
from src.errors import ConfigError
from src.eval.denoise_eval import SCORES
from src.report.claims import CATEGORIES, ENGLISH_DOCUMENTS, TALLIED, Case, Claim, Rule
from src.report.claims import load_claims as parse_claims_file
from src.tracking.run_config import flatten_config
from tests.conftest import ROOT, one_line_error
from tests.test_ledger import CLAIM
from tests.test_sweeps import compose_sweep, swept

CONF_DIR = ROOT / "conf"
CLAIMS_FILE = CONF_DIR / "claims.yaml"
TOP_KEYS = {
    "id",
    "category",
    "source",
    "statement",
    "profiles",
    "needs",
    "runs",
    "metric",
    "per",
    "higher",
    "log",
    "rule",
}
#: Keys a claim may leave out: `caveat` (what its meaning needs of the seed's hardware or data).
OPTIONAL_TOP_KEYS = {"caveat"}
SOURCE_KEYS = {"document", "section", "where"}
#: `quote` is required for findings and readings, `translation` for a quote not in English.
OPTIONAL_SOURCE_KEYS = {"quote", "translation", "budget"}
DOCUMENTS = {"Bunjevac 2019", "Davletaliyev 2016", "Grujčić 2023", "Zhu et al. 2023"}
RUN_SOURCES = ("study", "pipeline", "bench")
RUN_KEYS = {*RUN_SOURCES, "experiment", "where"}
PER = {"image", "run", "round"}
NEEDS = {None, "gpu", "user_data"}
RULE_KEYS = {
    "better": {"kind", "a", "b", "b_metric", "size", "ratio", "b_distinct"},
    "comparable": {"kind", "a", "b", "b_metric", "tolerance", "tolerance_source", "ratio", "b_distinct"},
    "not_worse": {"kind", "a", "b", "b_metric", "tolerance", "tolerance_source", "ratio", "b_distinct"},
    "agreement": {"kind", "tolerance", "tolerance_source", "published"},
}
#: Rules whose tolerance must say where it comes from (a citation of the seed, or "project's own: ...").
TOLERANCE_SOURCE_KINDS = {"comparable", "not_worse", "agreement"}
OWN_TOLERANCE = "project's own"
#: Paragraphs of the Zhu et al. 2023 summary (one per line, the title line not counted; conf/claims.yaml's
#: section header): a `where` citing "paragraph N" must name one of them.
ZHU_PARAGRAPHS = 7
PROFILES = {p.stem for p in (CONF_DIR / "profile").glob("*.yaml")}
#: `python -m src.bench denoise --log`: experiment, and the `model` values of its bench/rounds.csv.
BENCH = {"denoise": ("nrbench-bench", {"unet_kpcn", "kpcn", "kpcn_frame", "oidn"})}
#: The bench params a speed claim may select runs by, and their values.
BENCH_WHERE = {"autocast": set(AUTOCAST_DTYPES)}
#: The project's own agreement tolerances for PSNR and SSIM (in the spirit of NerfBaselines' reproduction
#: checks, which publish no such threshold): changing one is a decision, so it is pinned here.
AGREEMENT_TOLERANCE = {"psnr": 0.2, "ssim": 0.05}

# --- what the runs log -----------------------------------------------------------------------------------
#: per_image.csv columns (src/eval/denoise_eval.py's SCORES and their noisy_* twins, the timings; a NeRF
#: view's row adds rays_per_s).
IMAGE_METRICS = {
    *SCORES,
    *(f"{prefix}_{s}" for s in SCORES for prefix in ("noisy", "baseline")),
    *("ms_per_image", "ms_per_mpixel", "rays_per_s"),
}
#: Losses the training objectives log (src/objectives/terms.py) as train_loss_<k> / val_loss_<k>.
LOSSES = ("diffuse", "specular", "color", "temporal", "total")
#: Run metrics logged under a literal name, and the module that logs each.
LITERAL_RUN_METRICS = {
    "param_count": "src/eval/loop.py",
    "train_time_s": "src/train/loop.py",
    "train_time_per_epoch_s": "src/train/trainer.py",
    "steps": "src/train/loop.py",
    "search_best": "src/tasks/filter_search.py",
    "search_best_so_far": "src/tasks/filter_search.py",
    "search_seconds": "src/tasks/filter_search.py",
    "search_best_initial": "src/gp/run_metrics.py",
    "search_best_midway": "src/gp/run_metrics.py",
    "search_feature_top_rival": "src/gp/run_metrics.py",
}
#: Occurrences of each feature in a search's best expression (`search_feature_<name>`, src/gp/run_metrics.py).
FEATURE_RUN_METRICS = {
    f"search_feature_{name}" for name in ("normal", "texture", "depth", "directIllumination")
}
RUN_METRICS = {
    *LITERAL_RUN_METRICS,
    *FEATURE_RUN_METRICS,
    *(f"eval_{s}" for s in IMAGE_METRICS),
    *(f"{split}_loss_{k}" for split in ("train", "val") for k in LOSSES),
}
#: Scores where higher is better; every other score the claims use is an error, a loss or a time.
HIGHER_BETTER = {"psnr", "ssim", "tpsnr", "rays_per_s", "search_feature_normal"}  # (the last: more use)
#: A run's two measures of one quantity that a claim may pair (metric, b_metric): a search's error at its end
#: and at its start or middle; the normal's use and its most used rival's.
SAME_QUANTITY = {
    ("search_best_so_far", "search_best_initial"),
    ("search_best_so_far", "search_best_midway"),
    ("search_feature_normal", "search_feature_top_rival"),
}
#: Positive, scale-free scores whose ratios (log: true) mean something: errors, losses, times (a training's
#: wall-clock train_time_s among them).
RATIO_SCORES = re.compile(
    r"^(relmse.*|mse|smape|ms_per_.*|seconds|.*loss_.*|search_best.*|search_seconds|train_time_s|train_time_per_epoch_s)$"
)


def load_claims(path: Path = CLAIMS_FILE) -> list[dict]:
    return OmegaConf.to_container(OmegaConf.load(path), resolve=True)["claims"]


CLAIMS = load_claims()
IDS = [c["id"] for c in CLAIMS]


def score_name(metric: str) -> str:
    """The score a metric measures: `eval_psnr` -> psnr, `noisy_relmse` -> relmse (also `baseline_`)."""
    return re.sub(r"^(eval_)?(noisy_|baseline_)?", "", metric)


def arms(claim: dict) -> list[tuple[dict, dict]]:
    """Every (arm, where) the claim compares: a and b, or each published case; `where` includes the runs'."""
    rule, where = claim["rule"], claim["runs"].get("where") or {}
    if rule["kind"] == "agreement":
        return [(case["arm"], {**where, **(case.get("where") or {})}) for case in rule["published"]]
    return [(rule["a"], where), (rule["b"], where)]


# --- the study's jobs ------------------------------------------------------------------------------------
def _group_file(group: str, option: str) -> tuple[Path, bool]:
    """conf/<group>/<option>.yaml and whether it is `# @package _global_`."""
    path = CONF_DIR / group / f"{option}.yaml"
    return path, "@package _global_" in path.read_text().split("\n", 1)[0]


def _apply(cfg: DictConfig, key: str, value) -> None:
    """One swept value into a job config, as Hydra would: a config group's option (model=kpcn,
    +selection_arm=random) merges its file, a dict merges into the node, anything else replaces the value."""
    group = key.lstrip("+")
    if (CONF_DIR / group).is_dir() and isinstance(value, str):
        path, is_global = _group_file(group, value)
        node = OmegaConf.load(path)
        node.pop("defaults", None)
        OmegaConf.set_struct(cfg, False)
        if is_global:  # a `_global_` file merges into the nodes it names
            for k in node:
                cfg[k] = OmegaConf.merge(cfg[k], node[k]) if k in cfg else node[k]
        else:  # another option of the group replaces the node (the keys read here are in the file)
            cfg[group] = node
    elif isinstance(value, dict):
        OmegaConf.update(cfg, key, value, merge=True, force_add=True)
    else:
        OmegaConf.update(cfg, key, value, merge=False, force_add=True)


@cache
def study(name: str, profile: str) -> tuple[DictConfig, tuple[DictConfig, ...], frozenset[str]]:
    """(the study's base config, one config per job with the seeds left out, the keys it varies)."""
    base = compose_sweep(name, [f"profile={profile}"])
    swept_values: dict[str, list] = {}
    varied: set[str] = set()
    for key, override in swept(base).items():
        if key == "seed":
            continue
        value = override.value()
        values = list(value.list) if override.is_sweep_override() else [value]
        swept_values[key] = values
        group = key.lstrip("+")
        if (CONF_DIR / group).is_dir() and all(isinstance(v, str) for v in values):
            for v in values:  # a group option varies the keys its file sets
                path, is_global = _group_file(group, v)
                node = OmegaConf.load(path)
                node.pop("defaults", None)
                flat = flatten_config(OmegaConf.create(node if is_global else {group: node}))
                varied |= set(flat)
        elif all(isinstance(v, dict) for v in values):
            varied |= {f"{key}.{k}" for v in values for k in v}
        else:
            varied.add(key)
    jobs = []
    for combination in itertools.product(*swept_values.values()):
        job = copy.deepcopy(base)
        for key, value in zip(swept_values, combination, strict=True):
            _apply(job, key, value)
        jobs.append(job)
    return base, tuple(jobs), frozenset(varied | set(base.report.axes))


def logged(cfg: DictConfig, key: str) -> str:
    """The MLflow param value of config key `key` (as `flatten_config` logs it); KeyError if absent."""
    value = OmegaConf.select(cfg, key, default=KeyError)
    if value is KeyError:
        raise KeyError(key)
    return flatten_config({"value": value})["value"]


def matches(job: DictConfig, wanted: dict) -> bool:
    try:
        return all(logged(job, k) == v for k, v in wanted.items())
    except KeyError:
        return False


# --- the checks ------------------------------------------------------------------------------------------
def schema_errors(claims: list[dict]) -> list[str]:
    """Everything wrong with the claims' keys and values that needs no config composed."""
    errors, seen = [], set()
    for i, c in enumerate(claims):
        name = c.get("id", f"claims[{i}]")
        if not TOP_KEYS <= set(c) <= TOP_KEYS | OPTIONAL_TOP_KEYS:
            wrong = (TOP_KEYS - set(c)) | (set(c) - TOP_KEYS - OPTIONAL_TOP_KEYS)
            errors.append(f"{name}: keys {sorted(wrong)} missing or unknown")
            continue
        if not re.fullmatch(r"[a-z][a-z0-9_]*", name) or name in seen:
            errors.append(f"{name}: id not snake_case or not unique")
        seen.add(name)
        source = c["source"]
        if (
            not isinstance(source, dict)
            or not SOURCE_KEYS <= set(source) <= SOURCE_KEYS | OPTIONAL_SOURCE_KEYS
            or source["document"] not in DOCUMENTS
        ):
            errors.append(f"{name}: source {source}")
            continue
        if not isinstance(source["section"], str) or not isinstance(source["where"], str):
            errors.append(f"{name}: source.section and source.where must be strings")
        errors += metadata_errors(name, c)
        statement = c["statement"]
        if not isinstance(statement, str) or not statement.strip().endswith(".") or "/work" in statement:
            errors.append(f"{name}: statement {statement!r}")
        profiles = c["profiles"]
        if not profiles or not set(profiles) <= PROFILES or len(set(profiles)) != len(profiles):
            errors.append(f"{name}: profiles {profiles}; expected some of {sorted(PROFILES)}")
        if c["needs"] not in NEEDS or c["needs"] != expected_needs(c):
            errors.append(
                f"{name}: needs {c['needs']!r}; expected {expected_needs(c)!r} for profiles {profiles}"
            )
        runs = c["runs"]
        sources = [s for s in RUN_SOURCES if s in runs]
        allowed = (["study"], ["pipeline"], ["study", "pipeline"], ["bench"])
        if not set(runs) <= RUN_KEYS or sources not in allowed or not isinstance(runs.get("experiment"), str):
            errors.append(f"{name}: runs {runs}; expected one of {allowed} and an experiment")
            continue
        if c["per"] not in PER or (c["per"] == "round") != (sources[0] == "bench"):
            errors.append(f"{name}: per {c['per']!r} with runs.{sources[0]}")
        metric, per = c["metric"], c["per"]
        known = {"image": IMAGE_METRICS, "run": RUN_METRICS, "round": {"seconds"}}.get(per, set())
        if metric not in known:
            errors.append(f"{name}: metric {metric!r} is not logged per {per}")
        if not isinstance(c["higher"], bool) or not isinstance(c["log"], bool):
            errors.append(f"{name}: higher and log must be booleans")
        rule = c["rule"]
        kind = rule.get("kind")
        if kind not in RULE_KEYS or not set(rule) <= RULE_KEYS[kind]:
            errors.append(f"{name}: rule {rule}")
            continue
        if kind != "agreement":
            if c["higher"] != (score_name(metric) in HIGHER_BETTER):
                errors.append(f"{name}: higher {c['higher']} for {metric}")
            b_metric = rule.get("b_metric")
            if not rule.get("a") or not rule.get("b") or (rule["a"] == rule["b"] and b_metric is None):
                errors.append(f"{name}: arms a and b must differ (or b have its b_metric) and be non-empty")
            same = score_name(b_metric or "") == score_name(metric) or (metric, b_metric) in SAME_QUANTITY
            if b_metric is not None and (b_metric not in known or not same):
                errors.append(
                    f"{name}: b_metric {b_metric!r}: not logged per {per}, or not {metric} of another method"
                )
        if c["log"] and not RATIO_SCORES.match(score_name(metric)):
            errors.append(f"{name}: log: true for {metric}, which is not a ratio scale")
        if kind == "better" and rule.get("size") is not None:
            floor = 1.0 if c["log"] else 0.0  # a factor when log, else metric units
            if not isinstance(rule["size"], int | float) or rule["size"] < floor:
                errors.append(f"{name}: size {rule['size']!r}; expected a number >= {floor}")
        if kind in ("comparable", "not_worse") and not (
            isinstance(rule.get("tolerance"), int | float) and rule["tolerance"] > 0
        ):
            errors.append(f"{name}: {kind} tolerance {rule.get('tolerance')!r}; expected > 0")
        if kind in TOLERANCE_SOURCE_KINDS:
            tolerance_source = rule.get("tolerance_source")
            if not isinstance(tolerance_source, str) or not tolerance_source.strip():
                errors.append(
                    f"{name}: rule.tolerance_source missing; a {kind} rule says where its tolerance is from"
                )
            elif not (
                tolerance_source.startswith(OWN_TOLERANCE) or c["source"]["document"] in tolerance_source
            ):
                errors.append(
                    f"{name}: rule.tolerance_source {tolerance_source!r}; expected {OWN_TOLERANCE!r} and a "
                    f"reason, or a citation of {c['source']['document']}"
                )
        ratio = rule.get("ratio")
        if ratio is not None and not (
            isinstance(ratio, dict)
            and ratio
            and all(isinstance(v, int | float) and not isinstance(v, bool) and v > 0 for v in ratio.values())
        ):
            errors.append(f"{name}: rule.ratio {ratio!r}; expected {{budget key: b's value / a's, > 0}}")
        if kind == "agreement":
            if c["log"] or not rule.get("published") or not isinstance(rule.get("tolerance"), int | float):
                errors.append(f"{name}: agreement needs published cases, a tolerance and log: false")
                continue
            wanted = AGREEMENT_TOLERANCE.get(score_name(metric))
            if wanted is not None and rule["tolerance"] != wanted:
                errors.append(f"{name}: tolerance {rule['tolerance']} for {metric}; expected {wanted}")
            for case in rule["published"]:
                if set(case) - {"arm", "where", "value"} or not case.get("arm"):
                    errors.append(f"{name}: published case {case}")
                elif not isinstance(case.get("value"), int | float):
                    errors.append(f"{name}: published value {case.get('value')!r}")
        for arm, where in arms(c):
            for k, v in {**arm, **where}.items():
                if not isinstance(v, str):
                    errors.append(f'{name}: {k}: {v!r}; expected the string MLflow logs (e.g. "True")')
    return errors


def expected_needs(c: dict) -> str | None:
    """What a claim's profiles need: nothing at cpu or smoke, the user's scenes at thesis, else (paper
    only) a GPU, except for a set-up check (a parameter count), which the tests make on a CPU in seconds."""
    profiles = set(c["profiles"])
    if profiles & {"cpu", "smoke"}:
        return None
    if "thesis" in profiles:
        return "user_data"
    return None if c["category"] == "setup" else "gpu"


def metadata_errors(name: str, c: dict) -> list[str]:
    """The claim's category, quote, translation, `where` and caveat: a finding or reading quotes the seed
    sentence it rests on (in the seed's language, translated unless the seed is in English)."""
    errors = []
    category, source = c["category"], c["source"]
    if category not in CATEGORIES:
        errors.append(f"{name}: category {category!r}; expected one of {list(CATEGORIES)}")
    texts = {k: source.get(k) for k in OPTIONAL_SOURCE_KEYS} | {"caveat": c.get("caveat")}
    for key, text in texts.items():
        if text is not None and (not isinstance(text, str) or not text.strip()):
            errors.append(f"{name}: {key} {text!r}; expected text (or no key)")
    quote, translation = (source.get(k) or "" for k in ("quote", "translation"))
    if category in TALLIED and not str(quote).strip():
        errors.append(f"{name}: a {category} quotes the seed sentence it rests on; source.quote missing")
    if quote and not translation and source["document"] not in ENGLISH_DOCUMENTS:
        errors.append(f"{name}: source.translation missing; a quote from {source['document']} needs one")
    if translation and not quote:
        errors.append(f"{name}: source.translation without a quote")
    where = source.get("where")
    if quote and isinstance(where, str) and not where.strip():
        errors.append(f"{name}: source.where empty; a quote says where in the seed it is")
    if source["document"] == "Zhu et al. 2023" and isinstance(where, str):
        cited = [int(n) for n in re.findall(r"paragraph (\d+)", where)]
        if (quote and not cited) or not all(1 <= n <= ZHU_PARAGRAPHS for n in cited):
            errors.append(f"{name}: where {where!r}; expected 'paragraph N', N from 1 to {ZHU_PARAGRAPHS}")
    for key, text in {**texts, "where": where}.items():
        if isinstance(text, str) and ("/work" in text or "shared/" in text):
            errors.append(f"{name}: {key} names a local path")
    return errors


def bench_errors(c: dict) -> list[str]:
    experiment, models = BENCH.get(c["runs"]["bench"], (None, set()))
    errors = [] if c["runs"]["experiment"] == experiment else [f"{c['id']}: bench experiment"]
    for arm, where in arms(c):
        if set(arm) != {"model"} or arm["model"] not in models:
            errors.append(f"{c['id']}: bench arm {arm}; expected {{model: one of {sorted(models)}}}")
        for key, value in where.items():  # a bench run's params (src/bench/denoise.py::_params)
            if key not in BENCH_WHERE or str(value) not in BENCH_WHERE[key]:
                errors.append(f"{c['id']}: bench where {key}={value}; expected one of {BENCH_WHERE}")
    return errors


#: The DVC pipeline's parts (dvc.yaml's report names): their MLflow experiment and conf/compare.yaml section.
PIPELINES = {
    "denoise": ("nrbench-denoise", "denoise"),
    "volumetric": ("nrbench-denoise-volumetric", "volumetric"),
    "nerf": ("nrbench-nerf", "nerf"),
}


def pipeline_errors(c: dict) -> list[str]:
    """The pipeline part exists and logs to the claim's experiment; its arms are models (and scenes) that
    part of dvc.yaml runs (conf/compare.yaml)."""
    dvc_names = set(re.findall(r"report\.name=(\w+)", (ROOT / "dvc.yaml").read_text()))
    name = c["runs"]["pipeline"]
    if name not in PIPELINES or name not in dvc_names:
        return [f"{c['id']}: pipeline {name!r}; expected one of {sorted(dvc_names)}"]
    experiment, section = PIPELINES[name]
    part = yaml.safe_load((CONF_DIR / "compare.yaml").read_text())[section]
    models = {m for k in ("learned", "baselines", "models") for m in part.get(k, [])}
    errors = [] if c["runs"]["experiment"] == experiment else [f"{c['id']}: pipeline experiment"]
    for arm, where in arms(c):
        if set(arm) != {"model.name"} or arm["model.name"] not in models:
            errors.append(f"{c['id']}: pipeline arm {arm}; expected {{model.name: one of {sorted(models)}}}")
        if "task.scene" in where and where["task.scene"] not in part.get("scenes", []):
            errors.append(f"{c['id']}: the pipeline runs no scene {where['task.scene']!r}")
    return errors


def study_errors(c: dict) -> list[str]:
    """The study exists, composes at every listed profile that runs its task, logs to the claim's
    experiment, and has a job for every arm (with the claim's `where`)."""
    name, study_name = c["id"], c["runs"]["study"]
    if not (CONF_DIR / "sweep" / f"{study_name}.yaml").is_file():
        return [f"{name}: no conf/sweep/{study_name}.yaml"]
    errors = []
    for profile in c["profiles"]:
        base, jobs, varied = study(study_name, profile)
        if base.task.name not in base.profile_tasks:
            errors.append(f"{name}: profile {profile} does not run task {base.task.name}")
            continue
        experiment = OmegaConf.select(base, "tracking.experiment")
        if experiment != c["runs"]["experiment"]:
            errors.append(f"{name}: experiment {c['runs']['experiment']!r}; the study logs to {experiment!r}")
        for arm, where in arms(c):
            for key in arm:
                if key not in varied:
                    errors.append(f"{name}: arm key {key!r} is not varied by {study_name} ({sorted(varied)})")
            wanted = {**arm, **where}
            if not any(matches(job, wanted) for job in jobs):
                errors.append(f"{name}: no job of {study_name} at profile={profile} has {wanted}")
    return errors


# --- tests -----------------------------------------------------------------------------------------------
def test_claims_file_loads_with_omegaconf_and_has_the_issues_claims():
    assert len(CLAIMS) >= 40
    ids = set(IDS)
    for wanted in (
        "kpcn_beats_dpcn",
        "shared_beats_separate_validation",
        "whitening_hurts_specular",
        "gp_expr1_beats_cross_bilateral",
        "gp_search_beats_cross_bilateral",
        "gp_expansion_default_beats_koza_crossover",
        "gp_population_no_clear_effect",
        "unet_kpcn_10x_faster_than_kpcn",
        "unet_kpcn_quality_comparable_to_kpcn",
        "selected_features_close_to_all",
        "selected_features_beat_random",
        "temporal_loss_reduces_flicker",
        "refnerf_beats_mipnerf_glossy",
        "nerf_parameter_count",
        "mipnerf_parameter_count",
        "refnerf_parameter_count",
    ):
        assert wanted in ids, wanted
    # The NeRF thesis's Tables 6.1-6.5: one claim per table and metric, three models each.
    for scene in ("lego", "materials", "drums", "chair", "ship"):
        for metric in ("psnr", "ssim", "lpips"):
            claim = CLAIMS[IDS.index(f"nerf_thesis_{scene}_{metric}")]
            assert claim["metric"] == f"eval_{metric}"
            cases = claim["rule"]["published"]
            assert [c["arm"]["model.name"] for c in cases] == ["nerf", "mipnerf", "refnerf"]
            assert all(c["where"] == {"task.scene": scene} for c in cases)


def test_every_claim_has_the_schemas_keys_and_allowed_values():
    assert schema_errors(CLAIMS) == []


def test_the_ledgers_parser_reads_every_claim_with_its_metadata():
    """src.report.claims reads the file as the ledger will: every claim, its category and quote."""
    parsed = {claim.id: claim for claim in parse_claims_file(CLAIMS_FILE)}
    assert list(parsed) == IDS
    for raw in CLAIMS:
        claim = parsed[raw["id"]]
        assert claim.category == raw["category"]
        assert bool(claim.quote) == bool(raw["source"].get("quote"))
        assert claim.tallied == (raw["category"] in TALLIED)


def test_set_up_checks_and_targets_are_the_ones_no_seed_finding_states():
    """Parameter counts and the iteration count are set-up checks; the speed factors, the OIDN bound and the
    U-Net's quality are the project's targets (the talk states none of them); the GP filters' timings are
    read on a GPU only, where the thesis timed them."""
    by_id = dict(zip(IDS, CLAIMS, strict=True))
    setup = {
        "dpcn_kpcn_parameter_counts",
        "residual_kpcn_parameter_count",
        "nerf_thesis_iterations",
        "nerf_parameter_count",
        "mipnerf_parameter_count",
        "refnerf_parameter_count",
    }
    targets = {
        "unet_kpcn_10x_faster_than_kpcn",
        "unet_kpcn_10x_faster_than_kpcn_frame",
        "unet_kpcn_within_2x_of_oidn",
        "unet_kpcn_quality_comparable_to_kpcn",
    }
    assert {i for i, c in by_id.items() if c["category"] == "setup"} == setup
    assert {i for i, c in by_id.items() if c["category"] == "target"} == targets
    for n in (1, 2, 3):
        claim = by_id[f"gp_expr{n}_time_comparable_to_cross_bilateral"]
        assert (claim["profiles"], claim["needs"]) == (["paper"], "gpu")
        assert claim.get("caveat")


@cache
def _budget(study_name: str, profile: str, model: str, key: str):
    """The value of a budget key for one model in a study at a profile, as the job would compose it (the
    model's own profile files, e.g. conf/model_task_profile/dpcn_paper.yaml, included)."""
    return OmegaConf.select(compose_sweep(study_name, [f"profile={profile}", f"model={model}"]), key)


#: Budget keys whose difference between two model arms is a confound unless the claim declares its ratio.
BUDGET_KEYS = ("task.train.epochs",)


@pytest.mark.parametrize(
    "claim",
    [c for c in CLAIMS if c["runs"].get("study") and c["rule"]["kind"] != "agreement"],
    ids=lambda c: c["id"],
)
def test_model_arms_budgets_differ_only_by_the_declared_ratio(claim):
    """Where the arms are two models, the budget each trains with at every profile the claim lists is
    the same, or differs by exactly the claim's `rule.ratio` (b / a): DPCN's doubled epochs."""
    rule = claim["rule"]
    ratio = rule.get("ratio") or {}
    if set(rule["a"]) != {"model.name"} or set(rule["b"]) != {"model.name"}:
        assert not ratio, f"{claim['id']}: a ratio needs two model arms here"
        return
    for profile in claim["profiles"]:
        for key in {*BUDGET_KEYS, *ratio}:
            a, b = (
                _budget(claim["runs"]["study"], profile, arm["model.name"], key)
                for arm in (rule["a"], rule["b"])
            )
            if key in ratio:
                assert a and b and b / a == pytest.approx(ratio[key]), (claim["id"], profile, key, a, b)
            else:
                assert a == b, f"{claim['id']} at {profile}: {key} {a} against {b}; declare rule.ratio"


@pytest.mark.parametrize("claim", CLAIMS, ids=IDS)
def test_claim_names_runs_the_harness_produces(claim):
    runs = claim["runs"]
    if "bench" in runs:
        errors = bench_errors(claim)
    else:
        errors = (pipeline_errors(claim) if "pipeline" in runs else []) + (
            study_errors(claim) if "study" in runs else []
        )
    assert errors == []


def test_literal_run_metric_names_are_what_the_code_logs():
    """The catalogue above must follow the code: each literal metric name is in the module that logs it."""
    for metric, module in LITERAL_RUN_METRICS.items():
        assert f'"{metric}"' in (ROOT / module).read_text(), (metric, module)
    objectives = (ROOT / "src/objectives/terms.py").read_text()
    assert all(f'"{k}"' in objectives or f"`{k}`" in objectives for k in LOSSES)


def test_published_nerf_values_are_the_thesis_tables_by_value():
    """A few published numbers by value (Grujčić 2023, Tables 6.2 and 6.6), so an edited value is seen."""
    by_id = dict(zip(IDS, CLAIMS, strict=True))
    materials = {
        c["arm"]["model.name"]: c["value"] for c in by_id["nerf_thesis_materials_psnr"]["rule"]["published"]
    }
    assert materials == {"nerf": 30.45, "mipnerf": 30.58, "refnerf": 35.71}
    assert by_id["refnerf_beats_mipnerf_materials"]["rule"]["size"] == pytest.approx(35.71 - 30.58)
    counts = {
        i: by_id[i]["rule"]["published"][0]["value"]
        for i in ("nerf_parameter_count", "mipnerf_parameter_count")
    }
    assert counts == {"nerf_parameter_count": 1_200_000, "mipnerf_parameter_count": 612_000}


def test_parameter_count_tolerances_cover_the_harness_exact_counts():
    """The exact counts the harness builds (tests/test_nerf_models.py, tests/test_denoise_models.py) lie
    within each parameter-count claim's tolerance of the published figure."""
    exact = {"nerf": 1_191_688, "mipnerf": 612_740, "refnerf": 1_110_158}
    exact |= {"dpcn": 2 * 1_828_303, "kpcn": 2 * 2_923_741, "resnet": 972_217}
    for claim in CLAIMS:
        if claim["metric"] != "param_count":
            continue
        for case in claim["rule"]["published"]:
            count = exact[case["arm"]["model.name"]]
            assert abs(count - case["value"]) <= claim["rule"]["tolerance"], (claim["id"], count)


# --- the checks catch realistic typos (hand-made mutants of the file) --------------------------------------
def _mutant(tmp_path, old: str, new: str, count: int = 1) -> list[dict]:
    text = CLAIMS_FILE.read_text()
    assert old in text, old
    path = tmp_path / "claims.yaml"
    path.write_text(text.replace(old, new, count))
    return load_claims(path)


def _claim(claims: list[dict], claim_id: str) -> dict:
    return next(c for c in claims if c["id"] == claim_id)


@pytest.mark.parametrize(
    ("old", "new", "needle"),
    [
        ("- id: kpcn_beats_residual_kpcn", "- id: kpcn_beats_dpcn", "not unique"),
        ("profiles: [paper, cpu]", "profiles: [paper, cpuu]", "expected some of"),
        ("needs: user_data", "needs: gpu", "needs"),
        ("metric: val_loss_specular", "metric: val_loss_speculr", "not logged"),
        (
            "metric: psnr\n    per: image\n    higher: true",
            "metric: psnr\n    per: image\n    higher: false",
            "higher",
        ),
        ("tolerance: 0.2\n", "tolerance: 0.3\n", "tolerance"),
        ('model.shared: "True"', "model.shared: true", "expected the string"),
        ("rule: {kind: better, a: {model.name: kpcn}", "rule: {kind: beter, a: {model.name: kpcn}", "rule"),
        ("category: reading", "category: readings", "category"),
        (  # a target without a quote promoted to a finding
            "- id: unet_kpcn_within_2x_of_oidn\n    category: target",
            "- id: unet_kpcn_within_2x_of_oidn\n    category: finding",
            "source.quote missing",
        ),
        (
            "      translation: >-\n"
            "        The kernel-prediction approach proved better than direct prediction.\n",
            "",
            "translation missing",
        ),
        (
            "tolerance_source: \"project's own: the talk gives no number (and no quality",
            "# tolerance_source: \"project's own: the talk gives no number (and no quality",
            "tolerance_source missing",
        ),
        (
            "tolerance_source: >-\n        project's own:",
            "tolerance_source: >-\n        our own:",
            "tolerance_source",
        ),
        ("dpcn}, ratio: {task.train.epochs: 2}}", "dpcn}, ratio: {task.train.epochs: 0}}", "rule.ratio"),
        ('where: "paragraph 2"', 'where: "paragraph 8"', "paragraph N"),
        (  # the first nerf_variants claim, a parameter count, marked as needing a GPU again
            "needs: null\n    runs: {study: nerf_variants",
            "needs: gpu\n    runs: {study: nerf_variants",
            "needs",
        ),
        (
            "runs: {study: denoisers, experiment: nrbench-denoise}",
            "runs: {experiment: nrbench-denoise}",
            "runs",
        ),
    ],
)
def test_schema_checks_catch_a_typo(tmp_path, old, new, needle):
    errors = schema_errors(_mutant(tmp_path, old, new))
    assert any(needle in e for e in errors), errors


@pytest.mark.parametrize(
    ("claim_id", "old", "new", "needle"),
    [
        ("kpcn_beats_dpcn", "study: denoisers", "study: denoiser", "no conf/sweep/denoiser.yaml"),
        (
            "kpcn_beats_dpcn",
            "b: {model.name: dpcn}, ratio",
            "b: {model.name: dcpn}, ratio",
            "no job of denoisers",
        ),
        ("whitening_hurts_specular", 'b: {model.whiten: "True"}', 'b: {model.whiten: "true"}', "no job"),
        (
            "unet_kpcn_quality_comparable_to_kpcn",
            "experiment: nrbench-denoise-volumetric",
            "experiment: nrbench-denoise",
            "experiment",
        ),
        (
            "gp_population_no_clear_effect_cpu",
            'b: {task.search.population: "64"}',
            'b: {task.search.population: "400"}',
            "profile=cpu",
        ),
        (
            "refnerf_beats_mipnerf_glossy",
            "where: {task.scene: tabletop}",
            "where: {task.scene: table}",
            "no job",
        ),
        ("selected_features_beat_random", "order: random}", "ordering: random}", "not varied"),
    ],
)
def test_study_checks_catch_a_typo(tmp_path, claim_id, old, new, needle):
    claims = _mutant(tmp_path, old, new, count=1)
    errors = study_errors(_claim(claims, claim_id))
    assert any(needle in e for e in errors), errors


def test_bench_checks_catch_a_wrong_model():
    claim = copy.deepcopy(CLAIMS[IDS.index("unet_kpcn_10x_faster_than_kpcn")])
    assert bench_errors(claim) == []
    claim["rule"]["b"] = {"model": "kpcn_still"}
    assert any("bench arm" in e for e in bench_errors(claim))
    claim["rule"]["b"] = {"model.name": "kpcn"}
    assert any("bench arm" in e for e in bench_errors(claim))


def test_pipeline_checks_accept_the_dvc_report_names_only():
    claim = copy.deepcopy(CLAIMS[IDS.index("kpcn_beats_dpcn")])
    claim["runs"] = {"pipeline": "denoise", "experiment": "nrbench-denoise"}
    assert pipeline_errors(claim) == []
    claim["runs"]["pipeline"] = "denoising"
    assert any("pipeline" in e for e in pipeline_errors(claim))


#: Claims whose study keeps fewer seeds than the ledger's minimum replication, and why (the ledger reads
#: them "underpowered" and says what they would need).
SEED_LIMITED = {
    # One training per model and scene: 1M iterations each on the user's nerf_synthetic scenes.
    "refnerf_beats_mipnerf_drums": "nerf_thesis",
    "refnerf_beats_mipnerf_materials": "nerf_thesis",
}


def test_every_study_claim_runs_the_seeds_its_test_needs():
    """The ledger replicates a learned arm by its training seed (docs/ledger.md): a better or comparable
    claim read from a study can only be decided with at least `min_items` seeds (a signed-rank test over
    n seeds never gives p below 2 / 2^n), so its study must sweep that many, per image or per run."""
    from src.report.signed_rank import min_items

    needed = min_items(0.05)
    assert needed == 6
    for claim in CLAIMS:
        study = claim["runs"].get("study")
        if claim["rule"]["kind"] == "agreement" or not study:
            continue
        seed = swept(compose_sweep(study))["seed"]
        seeds = list(seed.sweep_string_iterator()) if seed.is_sweep_override() else [seed.value()]
        assert len(seeds) >= needed or SEED_LIMITED.get(claim["id"]) == study, (claim["id"], study, seeds)


# --- src.report.claims by value (mutation testing round 3: scripts/mutation.sh report_claims) ---------------
#: A small claims file of one claim (the ledger tests' own); the tests below edit one key each and read
#: what the parser makes of it.
ONE_CLAIM = CLAIM


def _parsed(tmp_path, text: str):
    path = tmp_path / "claims.yaml"
    path.write_text(text)
    return parse_claims_file(path)


def _refused(tmp_path, text: str, *needles: str) -> str:
    with pytest.raises(ConfigError) as excinfo:
        _parsed(tmp_path, text)
    return one_line_error(excinfo, *needles)


def test_the_claims_file_is_read_with_its_interpolations_resolved(tmp_path):
    """The file is OmegaConf YAML: `${...}` is resolved (here the experiment named once at the top), not
    kept as the literal text that no MLflow experiment is called."""
    text = "experiment: nrbench-denoise\nclaims:" + ONE_CLAIM.format(id="c").replace(
        "experiment: nrbench-denoise}", "experiment: '${experiment}'}"
    )
    (claim,) = _parsed(tmp_path, text)
    assert claim.experiment == "nrbench-denoise"


def test_a_file_without_a_non_empty_claims_list_is_refused(tmp_path):
    _refused(tmp_path, ONE_CLAIM.format(id="c"), "no `claims:` list")  # the list alone, not under claims:
    _refused(tmp_path, "claims: []\n", "no `claims:` list")
    _refused(tmp_path, "claims: {c: 1}\n", "no `claims:` list")
    _refused(tmp_path, "budgets: {}\n", "no `claims:` list")
    assert [c.id for c in _parsed(tmp_path, "claims:" + ONE_CLAIM.format(id="c"))] == ["c"]


def test_a_claim_without_an_id_is_named_by_its_position(tmp_path):
    second = ONE_CLAIM.format(id="x").replace("  - id: x\n    category", "  - category")
    _refused(tmp_path, "claims:" + ONE_CLAIM.format(id="c") + second, "claims[1].id", "None")


#: Three claims that set every key the parser reads, each away from its default, with runs of spaces and
#: line breaks in the texts a person wrote (the parser keeps one space between words).
FULL_CLAIMS = """
claims:
  - id: full_better
    category: reading
    source:
      document: Bunjevac 2019
      section: "6.2"
      where: Table 6.3
      quote: "Das  KPCN\\n   ist besser."
      translation: "KPCN   is\\n better."
      budget: "2   epochs"
    statement: "KPCN   beats\\n DPCN."
    caveat: "Seed  hardware\\n only."
    profiles: [paper, 7]
    needs: gpu
    runs: {pipeline: denoise, study: denoisers, experiment: nrbench-denoise, where: {task.scene: 3}}
    metric: relmse
    per: run
    higher: false
    log: true
    rule:
      kind: better
      a: {model.name: kpcn}
      b: {model.name: dpcn, model.depth: 4}
      size: 1.5
      ratio: {task.train.epochs: 0.5}
      b_distinct: {dataset.subset: 2}
  - id: full_comparable
    category: target
    source: {document: Davletaliyev 2016}
    statement: Same speed.
    profiles: [paper]
    runs: {bench: denoise, experiment: nrbench-bench}
    metric: seconds
    per: round
    higher: false
    rule:
      kind: comparable
      a: {model: unet}
      b: {model: unet}
      b_metric: baseline_seconds
      tolerance: 0.25
      tolerance_source: project's own
  - id: full_agreement
    category: setup
    source: {document: Grujčić 2023, section: "6"}
    statement: Table values.
    profiles: [thesis]
    runs: {study: nerf_thesis, experiment: nrbench-nerf}
    metric: eval_psnr
    per: image
    higher: true
    rule:
      kind: agreement
      tolerance: 2
      tolerance_source: thesis Table 6.1
      published:
        - {arm: {model.name: nerf}, where: {task.scene: lego}, value: 31}
        - {arm: {model.name: refnerf}, value: 33.5}
"""


def test_the_parser_keeps_every_key_of_a_claim_as_written(tmp_path):
    """Each claim equals the one written out by hand: no key dropped, defaulted or swapped, numbers and
    config values as strings (what MLflow logs), texts with single spaces."""
    better, comparable, agreement = _parsed(tmp_path, FULL_CLAIMS)
    assert better == Claim(
        id="full_better",
        document="Bunjevac 2019",
        section="6.2",
        where_stated="Table 6.3",
        statement="KPCN beats DPCN.",
        profiles=("paper", "7"),
        needs="gpu",
        sources=(("study", "denoisers"), ("pipeline", "denoise")),
        experiment="nrbench-denoise",
        where={"task.scene": "3"},
        metric="relmse",
        per="run",
        higher=False,
        log=True,
        rule=Rule(
            "better",
            a={"model.name": "kpcn"},
            b={"model.name": "dpcn", "model.depth": "4"},
            size=1.5,
            ratio={"task.train.epochs": 0.5},
            b_distinct={"dataset.subset": 2},
        ),
        category="reading",
        quote="Das KPCN ist besser.",
        translation="KPCN is better.",
        caveat="Seed hardware only.",
        seed_budget="2 epochs",
    )
    assert comparable == Claim(
        id="full_comparable",
        document="Davletaliyev 2016",
        section="",
        where_stated="",
        statement="Same speed.",
        profiles=("paper",),
        needs=None,
        sources=(("bench", "denoise"),),
        experiment="nrbench-bench",
        where={},
        metric="seconds",
        per="round",
        higher=False,
        log=False,
        rule=Rule(
            "comparable",
            a={"model": "unet"},
            b={"model": "unet"},
            tolerance=0.25,
            b_metric="baseline_seconds",
            tolerance_source="project's own",
        ),
        category="target",
    )
    assert agreement.rule == Rule(
        "agreement",
        tolerance=2.0,
        tolerance_source="thesis Table 6.1",
        published=(
            Case({"model.name": "nerf"}, {"task.scene": "lego"}, 31.0),
            Case({"model.name": "refnerf"}, {}, 33.5),
        ),
    )
    assert (agreement.citation, agreement.quote, agreement.caveat) == ("Grujčić 2023, Sec. 6", "", "")
    assert comparable.citation == "Davletaliyev 2016" and not comparable.tallied and better.tallied
    # How a user produces each claim's first-choice runs: the study before the pipeline, a bench alone.
    assert better.command("paper") == "python -m src.run -m +sweep=denoisers profile=paper"
    assert comparable.command("cpu") == "python -m src.bench denoise --profile cpu --log"
    assert (better.is_bench, comparable.is_bench) == (False, True)


def _rule_edit(old: str, new: str) -> str:
    """ONE_CLAIM with one edit, which must apply (a typo in the test would otherwise test nothing)."""
    text = "claims:" + ONE_CLAIM.format(id="c")
    assert old in text, old
    return text.replace(old, new)


def test_each_rule_limit_is_refused_on_one_side_and_accepted_on_the_other(tmp_path):
    comparable = "kind: comparable, tolerance_source: s, tolerance: {}"
    _refused(tmp_path, _rule_edit("kind: better", comparable.format(0)), "claims.c.rule.tolerance: 0.0")
    (c,) = _parsed(tmp_path, _rule_edit("kind: better", comparable.format(0.25)))
    assert c.rule.tolerance == 0.25
    distinct = "dpcn}}, b_distinct: {{seed: {}}}}}"
    _refused(tmp_path, _rule_edit("dpcn}}", distinct.format(1)), "claims.c.rule.b_distinct", "counts >= 2")
    (c,) = _parsed(tmp_path, _rule_edit("dpcn}}", distinct.format(2)))
    assert c.rule.b_distinct == {"seed": 2}
    # A ratio is a positive number: YAML's true is a boolean, though Python counts it as 1.
    ratio = "dpcn}}, ratio: {{task.train.epochs: {}}}}}"
    _refused(tmp_path, _rule_edit("dpcn}}", ratio.format("true")), "claims.c.rule.ratio", "positive")
    (c,) = _parsed(tmp_path, _rule_edit("dpcn}}", ratio.format(0.25)))
    assert c.rule.ratio == {"task.train.epochs": 0.25}


def test_a_rule_needs_both_arms_and_a_comparison_a_number(tmp_path):
    _refused(tmp_path, _rule_edit("b: {model.name: dpcn}", "b: {}"), "claims.c.rule: arms", "non-empty")
    _refused(tmp_path, _rule_edit("a: {model.name: kpcn}, ", ""), "claims.c.rule: arms", "non-empty")
    msg = _refused(
        tmp_path, _rule_edit("kind: better", "kind: comparable, tolerance_source: s, tolerance: x")
    )
    assert msg == "claims.c.rule.tolerance: 'x'; expected a int or float"
    # One arm scored by another metric of the same runs (a baseline logged beside the method).
    (c,) = _parsed(tmp_path, _rule_edit("b: {model.name: dpcn}", "b: {model.name: kpcn}, b_metric: base"))
    assert (c.rule.a, c.rule.b, c.rule.b_metric) == ({"model.name": "kpcn"},) * 2 + ("base",)


def test_a_claim_key_of_the_wrong_type_or_empty_is_refused_not_read_as_something_else(tmp_path):
    msg = _refused(tmp_path, _rule_edit("higher: true", 'higher: "true"'))  # a string, not a boolean
    assert msg == "claims.c.higher: 'true'; expected a bool"
    _refused(tmp_path, _rule_edit("profiles: [paper, cpu]", "profiles: []"), "claims.c.profiles: []")
    _refused(tmp_path, _rule_edit("study: denoisers, ", ""), "claims.c.runs: names none")
    # A typo in a published case names the case, as a typo in the rule names the rule.
    agreement = "kind: agreement, tolerance: 1, tolerance_source: s, published: [{value: 1}, {vaule: 2}]"
    text = _rule_edit("kind: better, a: {model.name: kpcn}, b: {model.name: dpcn}", agreement)
    _refused(tmp_path, text, "claims.c.rule.published[1]: unknown key(s) ['vaule']")


#: The rule of ONE_CLAIM, and an agreement rule to put in its place.
ONE = "kind: better, a: {model.name: kpcn}, b: {model.name: dpcn}"
AGREEMENT = "kind: agreement, tolerance: 1, tolerance_source: s, published: [{arm: {m: n}, value: 1}]"


@pytest.mark.parametrize(
    ("rule", "old", "new", "path"),
    [
        (ONE, "higher: true", "higher: true\n    metirc: psnr", "claims.c: unknown key(s) ['metirc']"),
        (ONE, "Table 6.3,", "Table 6.3, page: 4,", "claims.c.source: unknown key(s) ['page']"),
        (
            ONE,
            "experiment: nrbench-denoise}",
            "experiment: nrbench-denoise, sweep: x}",
            "claims.c.runs: unknown key(s) ['sweep']",
        ),
        (
            ONE,
            "{model.name: dpcn}}",
            "{model.name: dpcn}, sise: 1}",
            "claims.c.rule: unknown key(s) ['sise']",
        ),
        (ONE, "kind: better", "kind: bigger", "claims.c.rule.kind: 'bigger'"),
        (ONE, "per: image", "per: item", "claims.c.per: 'item'"),
        (ONE, "category: finding", "category: result", "claims.c.category: 'result'"),
        (ONE, "needs: gpu", "needs: cpu", "claims.c.needs: 'cpu'"),
        (ONE, "document: Bunjevac 2019, ", "", "claims.c.source.document: None"),
        (ONE, "statement: KPCN beats DPCN.", "", "claims.c.statement: None"),
        (ONE, "metric: psnr", "", "claims.c.metric: None"),
        (ONE, ", experiment: nrbench-denoise", "", "claims.c.runs.experiment: None"),
        (
            ONE,
            "experiment: nrbench-denoise}",
            "experiment: nrbench-denoise, where: x}",
            "claims.c.runs.where: 'x'",
        ),
        (ONE, "a: {model.name: kpcn}", "a: kpcn", "claims.c.rule.a: 'kpcn'"),
        (ONE, "b: {model.name: dpcn}", "b: dpcn", "claims.c.rule.b: 'dpcn'"),
        (ONE, "dpcn}}", "dpcn}, b_metric: 3}", "claims.c.rule.b_metric: 3"),
        (ONE, "kind: better", "kind: comparable, tolerance: 1", "claims.c.rule.tolerance_source: None"),
        (AGREEMENT, "tolerance: 1, tolerance_source: s, ", "", "claims.c.rule.tolerance: None"),
        (AGREEMENT, "tolerance_source: s, ", "", "claims.c.rule.tolerance_source: None"),
        (AGREEMENT, "arm: {m: n}", "arm: n", "claims.c.rule.published[0].arm: 'n'"),
        (AGREEMENT, "arm: {m: n}", "arm: {m: n}, where: n", "claims.c.rule.published[0].where: 'n'"),
        (AGREEMENT, "value: 1", "value: one", "claims.c.rule.published[0].value: 'one'"),
    ],
)
def test_a_malformed_key_is_named_by_its_full_path(tmp_path, rule, old, new, path):
    """The one-line error starts with the claim and the key's path in the file, whichever key it is."""
    text = "claims:" + ONE_CLAIM.format(id="c").replace("higher: true", "higher: true\n    needs: gpu")
    text = text.replace("kind: better, a: {model.name: kpcn}, b: {model.name: dpcn}", rule)
    assert old in text, old
    msg = _refused(tmp_path, text.replace(old, new, 1))
    assert msg.startswith(path), msg


#: ONE_CLAIM's source: its document, where it says so and the quote.
SOURCE = 'source: {document: Bunjevac 2019, section: "6.2", where: Table 6.3, quote: q, translation: t}'
PUBLISHED = "published: [{arm: {m: n}, value: 1}]"


@pytest.mark.parametrize(
    ("old", "new", "message"),
    [
        (PUBLISHED, "published: [31.5]", "claims.c.rule.published[0]: 31.5;"),
        (PUBLISHED, "published: {value: 1}", "claims.c.rule.published: {'value': 1};"),
        (SOURCE, "source: 3", "claims.c.source: 3;"),
        (SOURCE, "source: Bunjevac 2019", "claims.c.source: 'Bunjevac 2019';"),
    ],
)
def test_a_value_where_keys_or_a_list_belong_is_a_one_line_error(tmp_path, old, new, message):
    """Found by this round: a published value written without its case, or a source written as its
    document's name, stopped the ledger with Python's TypeError (or a list of the text's letters as
    unknown keys) instead of naming the key."""
    text = "claims:" + ONE_CLAIM.format(id="c").replace(ONE, AGREEMENT)
    assert old in text, old
    msg = _refused(tmp_path, text.replace(old, new))
    assert msg.startswith(message) and "expected a" in msg, msg


# Mutation testing (scripts/mutation.sh report_claims, claims.py's 586 mutants): the tests above kill 564
# by themselves; 20 more fail the ledger's claims-file tests (tests/test_ledger.py, in the group: the
# `b_metric` of an agreement rule, `not_worse` needing a tolerance, the default size 0, a ratio of 0, a
# bench beside a study, a quote in English, the document's budget, a repeated id). The two left are
# equivalent:
# - `log=bool(raw.get("log", None))` and `log=bool(raw.get("log"))`: a claim without `log` compares on a
#   linear scale either way, since bool(None) is False, the default written.
