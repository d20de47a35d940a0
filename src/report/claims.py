"""The reproduction ledger's claims (`conf/claims.yaml`): each published finding the harness can test, where
it is stated, how it is measured and at which profiles. This module reads and checks the file; what the
runs say about each claim is `src.report.ledger`'s job, and the statuses are `src.report.verdicts`'.

A claim names its runs (a sweep `study`, the DVC `pipeline`, or a `bench`), the metric and its direction,
and a rule (`better`, `comparable` or `agreement`); docs/ledger.md describes every key. A malformed file
is a one-line `ConfigError` naming the claim and the key.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from omegaconf import OmegaConf

from src.errors import ConfigError

RULE_KINDS = ("better", "comparable", "not_worse", "agreement")
#: What kind of statement a claim is (docs/ledger.md): `finding` (the seed states it: quoted), `reading`
#: (the harness's interpretation of a quoted sentence), `target` (the project's own goal, e.g. a speed
#: ratio: shown apart, never counted as the seed's), `setup` (a parameter count or the like: checked by the
#: tests, out of the tally).
CATEGORIES = ("finding", "reading", "target", "setup")
#: The categories the ledger's headline counts.
TALLIED = ("finding", "reading")
#: Documents written in English: their quotes need no translation.
ENGLISH_DOCUMENTS = ("Davletaliyev 2016",)
RUN_SOURCES = ("study", "pipeline", "bench")
PER_CHOICES = ("image", "run", "round")
NEEDS_CHOICES = (None, "gpu", "user_data")


@dataclass(frozen=True)
class Case:
    """One published number an `agreement` rule checks: the arm (param -> value), extra param filters
    (`where`, e.g. the scene) and the value."""

    arm: dict[str, str]
    where: dict[str, str]
    value: float


@dataclass(frozen=True)
class Rule:
    """`better`: arm `a` beats arm `b` (by at least `size`, in the metric's units or as a ratio when the
    claim compares logs); `comparable`: `a` and `b` within `tolerance`; `not_worse`: `a` at most
    `tolerance` behind `b` (a non-inferiority: "at worst on par"); `agreement`: each case within
    `tolerance` of its published value. `b_metric`: arm `b` is scored by this metric of its runs instead
    of the claim's (a baseline the runs evaluate beside their method on the same items, e.g. the filter
    search's `baseline_relmse_spp`); `a` and `b` may then be the same runs. `tolerance_source`: where a
    comparable or agreement tolerance comes from (a citation, or "project's own"). `ratio`: budget keys
    on which the arms differ by design, as b's value over a's (`{task.train.epochs: 2}`: DPCN trained
    twice as long as KPCN, as the thesis did); any other difference between the arms' runs is a
    confound. `b_distinct`: {key: n}, arm b's runs must hold at least n distinct values of the key (a
    baseline drawn at random per seed, e.g. random feature subsets, is more than one draw)."""

    kind: str
    a: dict[str, str] = field(default_factory=dict)
    b: dict[str, str] = field(default_factory=dict)
    size: float = 0.0
    tolerance: float = 0.0
    published: tuple[Case, ...] = ()
    b_metric: str | None = None
    tolerance_source: str = ""
    ratio: dict[str, float] = field(default_factory=dict)
    b_distinct: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class Claim:
    id: str
    document: str
    section: str
    where_stated: str
    statement: str
    profiles: tuple[str, ...]
    needs: str | None
    sources: tuple[tuple[str, str], ...]  # (study | pipeline | bench, its name), in the order they are tried
    experiment: str
    where: dict[str, str]
    metric: str
    per: str
    higher: bool
    log: bool
    rule: Rule
    category: str = "finding"
    quote: str = ""
    translation: str = ""
    caveat: str = ""
    seed_budget: str = ""  # what the seed spent on the runs behind the claim (`budgets:` or source.budget)

    @property
    def citation(self) -> str:
        """ "Bunjevac 2019, Sec. 6.2, Table 6.3"."""
        parts = [self.document, f"Sec. {self.section}" if self.section else "", self.where_stated]
        return ", ".join(p for p in parts if p)

    @property
    def tallied(self) -> bool:
        """Whether the headline counts this claim: a finding or reading of a seed, not a target or setup."""
        return self.category in TALLIED

    @property
    def is_bench(self) -> bool:
        return self.sources[0][0] == "bench"

    def command(self, profile: str) -> str:
        """How a user produces the claim's (first-choice) runs at `profile`."""
        kind, name = self.sources[0]
        if kind == "study":
            return f"python -m src.run -m +sweep={name} profile={profile}"
        if kind == "bench":
            return f"python -m src.bench {name} --profile {profile} --log"
        return f"dvc repro (profile: {profile} in params.yaml)"


def _strings(mapping: Any, key: str) -> dict[str, str]:
    if mapping is None:
        return {}
    if not isinstance(mapping, Mapping):
        raise ConfigError(f"{key}: {mapping!r}; expected a mapping of config keys to values")
    return {str(k): str(v) for k, v in mapping.items()}


#: The keys each part of a claim may have: a misspelt one (`tolerence`) is an error, not ignored.
KEYS = {
    "": {
        *("id", "category", "source", "statement", "caveat", "profiles", "needs", "runs"),
        *("metric", "per", "higher", "log", "rule"),
    },
    "source": {"document", "section", "where", "quote", "translation", "budget"},
    "runs": {*RUN_SOURCES, "experiment", "where"},
    "rule": {
        *("kind", "a", "b", "b_metric", "size", "tolerance", "tolerance_source", "published", "ratio"),
        "b_distinct",
    },
    "published": {"arm", "where", "value"},
}


def _known_keys(raw: Any, part: str, where: str) -> None:
    if not isinstance(raw, Mapping):  # a number or a text where keys belong (`source: Bunjevac 2019`)
        raise ConfigError(f"{where}: {raw!r}; expected a mapping with some of {sorted(KEYS[part])}")
    unknown = sorted(set(raw) - KEYS[part])
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) {unknown}; expected some of {sorted(KEYS[part])}")


def _get(raw: Mapping, key: str, where: str, kinds: type | tuple[type, ...] = str) -> Any:
    value = raw.get(key)
    if value is None or not isinstance(value, kinds):
        expected = kinds.__name__ if isinstance(kinds, type) else " or ".join(k.__name__ for k in kinds)
        raise ConfigError(f"{where}.{key}: {value!r}; expected a {expected}")
    return value


def _choice(value: Any, choices: tuple, key: str) -> Any:
    if value not in choices:
        raise ConfigError(f"{key}: {value!r}; expected one of {list(choices)}")
    return value


def _rule(raw: Any, where: str) -> Rule:
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{where}: {raw!r}; expected a mapping with a `kind`")
    _known_keys(raw, "rule", where)
    kind = _choice(raw.get("kind"), RULE_KINDS, f"{where}.kind")
    if kind == "agreement":
        cases = raw.get("published") or []
        if not isinstance(cases, list):  # one case written without its list
            raise ConfigError(f"{where}.published: {cases!r}; expected a list of cases (arm, where, value)")
        if not cases:
            raise ConfigError(f"{where}.published: empty; an agreement rule needs published values")
        for i, c in enumerate(cases):
            _known_keys(c, "published", f"{where}.published[{i}]")
        published = tuple(
            Case(
                _strings(c.get("arm"), f"{where}.published[{i}].arm"),
                _strings(c.get("where"), f"{where}.published[{i}].where"),
                float(_get(c, "value", f"{where}.published[{i}]", (int, float))),
            )
            for i, c in enumerate(cases)
        )
        if raw.get("b_metric") is not None:
            raise ConfigError(f"{where}.b_metric: an agreement rule has no arm b; expected no b_metric")
        return Rule(
            kind,
            tolerance=float(_get(raw, "tolerance", where, (int, float))),
            published=published,
            tolerance_source=_get(raw, "tolerance_source", where),
        )
    a, b = _strings(raw.get("a"), f"{where}.a"), _strings(raw.get("b"), f"{where}.b")
    b_metric = None if raw.get("b_metric") is None else _get(raw, "b_metric", where)
    if not a or not b or (a == b and b_metric is None):
        raise ConfigError(
            f"{where}: arms a={a} and b={b}; expected two different, non-empty arms (or the same one with "
            "b_metric)"
        )
    ratio = _ratios(raw.get("ratio"), f"{where}.ratio")
    extra = dict(
        b_metric=b_metric, ratio=ratio, b_distinct=_distinct(raw.get("b_distinct"), f"{where}.b_distinct")
    )
    if kind in ("comparable", "not_worse"):
        tolerance = float(_get(raw, "tolerance", where, (int, float)))
        if tolerance <= 0:
            raise ConfigError(f"{where}.tolerance: {tolerance}; expected > 0")
        source = _get(raw, "tolerance_source", where)
        return Rule(kind, a, b, tolerance=tolerance, tolerance_source=source, **extra)
    return Rule(kind, a, b, size=float(raw.get("size") or 0.0), **extra)


def _distinct(raw: Any, where: str) -> dict[str, int]:
    """`rule.b_distinct`: {config key: the least number of distinct values arm b's runs must hold}."""
    if raw is None:
        return {}
    if not isinstance(raw, Mapping) or not all(
        isinstance(n, int) and not isinstance(n, bool) and n >= 2 for n in raw.values()
    ):
        raise ConfigError(f"{where}: {raw!r}; expected a mapping of config keys to counts >= 2")
    return {str(k): int(n) for k, n in raw.items()}


def _ratios(raw: Any, where: str) -> dict[str, float]:
    """`rule.ratio`: {budget key: b's value / a's value}, each a positive number."""
    if raw is None:
        return {}
    if not isinstance(raw, Mapping) or not all(
        isinstance(v, int | float) and not isinstance(v, bool) and v > 0 for v in raw.values()
    ):
        raise ConfigError(f"{where}: {raw!r}; expected a mapping of budget keys to positive ratios (b / a)")
    return {str(k): float(v) for k, v in raw.items()}


def _runs_sources(raw: Any, where: str) -> tuple[tuple[str, str], ...]:
    """(kind, name) of the claim's run sources in the order tried: a study's seeds before the pipeline's
    one run per model; a bench alone."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"{where}: {raw!r}; expected a mapping")
    named = [s for s in RUN_SOURCES if raw.get(s)]
    if not named or ("bench" in named and len(named) > 1):
        raise ConfigError(
            f"{where}: names {named or 'none'} of {list(RUN_SOURCES)}; expected a study and/or the pipeline, "
            "or a bench alone"
        )
    return tuple((kind, str(raw[kind])) for kind in named)


def parse_claim(raw: Any, index: int, budgets: Mapping[str, str] | None = None) -> Claim:
    """One entry of `claims:`; a missing or malformed key is a one-line ConfigError naming it. `budgets`:
    each document's budget (the file's `budgets:`), the claim's seed budget unless its source.budget
    names one of its own."""
    if not isinstance(raw, Mapping):
        raise ConfigError(f"claims[{index}]: {raw!r}; expected a mapping")
    name = f"claims[{index}]" if not isinstance(raw.get("id"), str) else f"claims.{raw['id']}"
    claim_id = _get(raw, "id", name)
    _known_keys(raw, "", name)
    source = raw.get("source") or {}
    _known_keys(source, "source", f"{name}.source")
    profiles = raw.get("profiles")
    if not profiles or isinstance(profiles, str | Mapping):
        raise ConfigError(f"{name}.profiles: {profiles!r}; expected a non-empty list of profiles")
    runs = raw.get("runs") or {}
    sources = _runs_sources(runs, f"{name}.runs")
    _known_keys(runs, "runs", f"{name}.runs")
    per = _choice(raw.get("per"), PER_CHOICES, f"{name}.per")
    if (sources[0][0] == "bench") != (per == "round"):
        raise ConfigError(
            f"{name}.per: {per!r} with runs.{sources[0][0]}; expected per: round for a bench, only then"
        )
    category = _choice(raw.get("category"), CATEGORIES, f"{name}.category")
    document = _get(source, "document", f"{name}.source")
    quote = " ".join(str(source.get("quote") or "").split())
    translation = " ".join(str(source.get("translation") or "").split())
    if category in TALLIED and not quote:
        raise ConfigError(f"{name}.source.quote: missing; a {category} quotes the seed sentence it rests on")
    if quote and not translation and document not in ENGLISH_DOCUMENTS:
        raise ConfigError(f"{name}.source.translation: missing; expected an English translation of the quote")
    return Claim(
        id=claim_id,
        category=category,
        quote=quote,
        translation=translation,
        caveat=" ".join(str(raw.get("caveat") or "").split()),
        seed_budget=" ".join(str(source.get("budget") or (budgets or {}).get(document) or "").split()),
        document=document,
        section=str(source.get("section") or ""),
        where_stated=str(source.get("where") or ""),
        statement=" ".join(_get(raw, "statement", name).split()),
        profiles=tuple(str(p) for p in profiles),
        needs=_choice(raw.get("needs"), NEEDS_CHOICES, f"{name}.needs"),
        sources=sources,
        experiment=_get(runs, "experiment", f"{name}.runs"),
        where=_strings(runs.get("where"), f"{name}.runs.where"),
        metric=_get(raw, "metric", name),
        per=per,
        higher=bool(_get(raw, "higher", name, bool)),
        log=bool(raw.get("log", False)),
        rule=_rule(raw.get("rule"), f"{name}.rule"),
    )


def load_claims(path: str | Path) -> list[Claim]:
    """Every claim of the claims file at `path`, in file order; ids must be unique."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: not found; expected the ledger's claims file (ledger.claims)")
    try:
        raw = OmegaConf.to_container(OmegaConf.load(path), resolve=True)
    except Exception as err:  # a YAML syntax error: one line naming the file
        raise ConfigError(f"{path}: not valid YAML ({' '.join(str(err).split())[:200]})") from None
    entries = raw.get("claims") if isinstance(raw, Mapping) else None
    if not isinstance(entries, list) or not entries:
        raise ConfigError(f"{path}: no `claims:` list; expected one entry per claim")
    budgets = raw.get("budgets") or {}
    if not isinstance(budgets, Mapping) or not all(isinstance(v, str) for v in budgets.values()):
        raise ConfigError(f"{path}: budgets: {budgets!r}; expected a mapping of documents to budget texts")
    claims = [parse_claim(entry, i, budgets) for i, entry in enumerate(entries)]
    seen: set[str] = set()
    for claim in claims:
        if claim.id in seen:
            raise ConfigError(f"{path}: claim id {claim.id!r} appears twice; expected unique ids")
        seen.add(claim.id)
    return claims
