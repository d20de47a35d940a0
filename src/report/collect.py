"""Select the runs a report compares (`find_runs`) and find config differences it must warn about
(`differing_params`).

Runs are those of `mlflow.search_runs`: one row per run, columns `run_id`, `status`, `start_time`,
`params.<flattened config key>`, `metrics.<key>`, `tags.<key>`. Only FINISHED job runs count; sweep
parent runs (tag `nrbench.sweep_parent=true`) are never compared.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterable, Iterator, Mapping
from pathlib import Path
from typing import Any

import mlflow
import pandas as pd
from mlflow.tracking import MlflowClient
from mlflow.utils.mlflow_tags import MLFLOW_PARENT_RUN_ID

from src.errors import DataError
from src.provenance import ignored_param
from src.report.renamed_keys import renamed_params

log = logging.getLogger("nrbench.report")

#: The repository root: a page names a file under it relative to it, never by its machine path.
REPOSITORY = Path(__file__).resolve().parents[2]


def display_path(path: str | Path) -> str:
    """`path` relative to the repository when it lies inside it, else its file name: what a report or a
    committed file may print (a machine's absolute path means nothing on another machine)."""
    resolved = Path(path).expanduser().resolve()
    return (
        resolved.relative_to(REPOSITORY).as_posix() if resolved.is_relative_to(REPOSITORY) else resolved.name
    )


def store_name(uri: str) -> str:
    """A tracking store as a page prints it: a file or SQLite store by `display_path` ("mlflow.db",
    "sqlite:///mlflow.db"), a server by its URL without credentials."""
    uri = str(uri)
    scheme, sep, rest = uri.partition("://")
    if not sep:  # a bare path
        return display_path(uri)
    if scheme.startswith("sqlite") or scheme == "file":
        return f"{scheme}:///{display_path('/' + rest.lstrip('/'))}"
    host = rest.rsplit("@", 1)[-1]  # user:password@host: the credentials stay out of the page
    return f"{scheme}://{host}"


SWEEP_PARENT_TAG = "nrbench.sweep_parent"
SWEEP_DIR_TAG = "nrbench.sweep_dir"
GROUP_TAG = "nrbench.group"
KEEP_CHOICES = ("latest", "all")
#: Defaults of optional `report:` keys for a config that lacks them (a hand-built one: tests, a notebook,
#: `find_runs` on its own). conf/config.yaml sets every key, so `python -m src.run stage=report` never uses
#: these: absent `axes` compare models; absent `keep` keeps every run (nothing is dropped unasked).
DEFAULT_AXES = ("model.name",)
DEFAULT_KEEP = "all"
#: How a run that lacks a param compares: as this value, so runs with and without the param differ (and
#: two runs that both lack it match) instead of the missing value being dropped or equal to anything.
UNSET = "<unset>"


def config_value(cfg: Any, key: str, default: Any = None) -> Any:
    """`cfg.key` for a DictConfig, a dict or an object; `default` when absent or None."""
    if cfg is None:
        return default
    value = cfg.get(key, default) if hasattr(cfg, "get") else getattr(cfg, key, default)
    return default if value is None else value


def _as_list(value: Any) -> list[str]:
    if value is None:
        return []
    if isinstance(value, str):
        return [value]
    return [str(v) for v in value]


def _quote(value: Any) -> str:
    """A single-quoted MLflow filter literal."""
    return "'" + str(value).replace("'", "\\'") + "'"


def param_column(axis: str) -> str:
    """`model.name` -> `params.model.name` (a `params.`/`metrics.`/`tags.` column is kept as is)."""
    axis = str(axis)
    return axis if axis.startswith(("params.", "metrics.", "tags.")) else f"params.{axis}"


#: The answers of the store while `searches_cached` is active: {(uri, experiments, filter): runs} and
#: {(uri, "experiment", name): the experiment}.
_CACHE: dict[tuple, Any] | None = None


@contextlib.contextmanager
def searches_cached() -> Iterator[None]:
    """Within: a search already made (same store, experiments and filter) and an experiment already looked
    up by name are answered from memory. The ledger searches once per claim, source, profile and status,
    mostly the same few queries, and names
    the filter that left no run by searching again: against a tracking server over HTTP that was a minute
    per ledger. The store is read, not written, meanwhile."""
    global _CACHE
    outer, _CACHE = _CACHE, {} if _CACHE is None else _CACHE
    try:
        yield
    finally:
        _CACHE = outer


def _cached(key: tuple, ask: Callable[[], Any]) -> Any:
    """`ask()`, or its answer from memory inside `searches_cached`."""
    if _CACHE is None:
        return ask()
    if key not in _CACHE:
        _CACHE[key] = ask()
    return _CACHE[key]


def _search_runs(experiment_ids: list[str], where: str) -> pd.DataFrame:
    def ask() -> pd.DataFrame:
        return mlflow.search_runs(experiment_ids=experiment_ids, filter_string=where, output_format="pandas")

    key = (mlflow.get_tracking_uri(), tuple(experiment_ids), where)
    return _cached(key, ask).copy()  # a copy: a caller changing its frame leaves the memory as it was


def _experiment_named(name: str, uri: str):
    return _cached((uri, "experiment", name), lambda: MlflowClient().get_experiment_by_name(name))


def _search(experiment_ids: list[str], steps: Iterable[tuple[str, Any]]) -> pd.DataFrame:
    """Runs matching every step: an MLflow filter clause (str) or a predicate on the frame's rows."""
    steps = list(steps)
    where = " and ".join(s for _, s in steps if isinstance(s, str))
    runs = _search_runs(experiment_ids, where)
    runs = renamed_params(runs)  # runs logged before a key moved, under today's names
    if f"tags.{SWEEP_PARENT_TAG}" in runs:
        runs = runs[runs[f"tags.{SWEEP_PARENT_TAG}"] != "true"]
    for _, step in steps:
        if callable(step) and not runs.empty:
            runs = runs[step(runs)]
    return runs


def _sweep_parent_ids(experiment_ids: list[str], sweep_dir: str) -> list[str]:
    """Ids of the sweep parent runs whose `nrbench.sweep_dir` tag is `sweep_dir` (same resolved path)."""
    parents = mlflow.search_runs(
        experiment_ids=experiment_ids,
        filter_string=f"tags.`{SWEEP_PARENT_TAG}` = 'true'",
        output_format="pandas",
    )
    column = f"tags.{SWEEP_DIR_TAG}"
    if parents.empty or column not in parents:
        return []
    wanted = Path(sweep_dir).expanduser().resolve()
    same = parents[column].map(lambda d: isinstance(d, str) and Path(d).expanduser().resolve() == wanted)
    return [str(r) for r in parents.loc[same, "run_id"]]


#: The run statuses `find_runs` selects by: the finished runs, or those that ended in an error.
RUN_STATUSES = ("FINISHED", "FAILED")


def find_runs(report_cfg: Any, level: int = logging.INFO) -> pd.DataFrame:
    """FINISHED job runs selected by `report_cfg`, oldest first.

    Keys (all optional except `experiment`): `status` (FINISHED, or FAILED for the runs that ended in an
    error: the ledger counts those as their arm's losses), `tracking_uri` (else the current MLflow URI),
    `experiment` (a name or a list of names), `parent_run_id` (a sweep's parent: its children only),
    `sweep_dir` (matched to the parent runs' `nrbench.sweep_dir` tag), `group` (the runs' `nrbench.group`
    tag), `tags` ({key: value}), `filter` (a free MLflow filter string, e.g.
    "params.`task.train.lr` = '0.0001'"), `keep` + `axes` (see `keep_latest`). When nothing matches,
    raises `DataError` with one line naming the first filter that left no run. `level`: the log level of
    the line counting the runs (the ledger, which searches once per claim and source, keeps it quiet).
    """
    uri = config_value(report_cfg, "tracking_uri")
    if uri:
        mlflow.set_tracking_uri(str(uri))
    uri = mlflow.get_tracking_uri()
    names = _as_list(config_value(report_cfg, "experiment"))
    experiment_ids = _experiment_ids(names, uri)
    steps = _filter_steps(report_cfg, names, experiment_ids)
    runs = _matching_runs(experiment_ids, steps, config_value(report_cfg, "filter"), uri)
    runs = runs.sort_values("start_time", kind="stable") if "start_time" in runs else runs
    runs = _keep_selected(runs, report_cfg)
    log.log(level, "report: %d runs from experiment(s) %s", len(runs), ", ".join(names))
    return runs.reset_index(drop=True)


def _experiment_ids(names: list[str], uri: str) -> list[str]:
    """Ids of the experiments `report.experiment` names; an empty list or a missing name is a `DataError`."""
    if not names:
        raise DataError("report.experiment is empty: name the MLflow experiment(s) to report on")
    experiment_ids = []
    for name in names:
        experiment = _experiment_named(name, uri)
        if experiment is None or experiment.lifecycle_stage == "deleted":
            raise DataError(f"report.experiment={name!r}: no such MLflow experiment in {uri}")
        experiment_ids.append(experiment.experiment_id)
    return experiment_ids


def _filter_steps(report_cfg: Any, names: list[str], experiment_ids: list[str]) -> list[tuple[str, Any]]:
    """(what the user set, MLflow clause or row predicate) per filter of `report_cfg`, applied
    cumulatively so that an empty result names its culprit."""
    status = str(config_value(report_cfg, "status", "FINISHED"))
    if status not in RUN_STATUSES:
        raise DataError(f"report.status={status!r}: expected one of {list(RUN_STATUSES)}")
    steps: list[tuple[str, Any]] = [
        (f"report.experiment={names if len(names) > 1 else names[0]!r}", f"attributes.status = '{status}'")
    ]
    steps += _sweep_steps(report_cfg, names, experiment_ids)
    group = config_value(report_cfg, "group")
    if group:
        steps.append((f"report.group={group!r}", f"tags.`{GROUP_TAG}` = {_quote(group)}"))
    tags: Mapping[str, Any] = config_value(report_cfg, "tags", {}) or {}  # no tags: no tag filter
    for key, value in tags.items():
        steps.append((f"report.tags.{key}={value!r}", f"tags.`{key}` = {_quote(value)}"))
    free = config_value(report_cfg, "filter")
    if free:
        steps.append((f"report.filter={str(free)!r}", str(free)))
    return steps


def _sweep_steps(report_cfg: Any, names: list[str], experiment_ids: list[str]) -> list[tuple[str, Any]]:
    """The step selecting one sweep's children, by `parent_run_id` or else by `sweep_dir`; none if
    neither is set. A `sweep_dir` without a parent run is a `DataError`."""
    parent_id = config_value(report_cfg, "parent_run_id")
    sweep_dir = config_value(report_cfg, "sweep_dir")
    if parent_id:
        return [(f"report.parent_run_id={parent_id!r}", f"tags.{MLFLOW_PARENT_RUN_ID} = {_quote(parent_id)}")]
    if not sweep_dir:
        return []
    parents = _sweep_parent_ids(experiment_ids, str(sweep_dir))
    if not parents:
        raise DataError(
            f"report.sweep_dir={str(sweep_dir)!r}: no sweep parent run with this "
            f"{SWEEP_DIR_TAG} tag in experiment(s) {names}"
        )
    column = f"tags.{MLFLOW_PARENT_RUN_ID}"
    return [
        (
            f"report.sweep_dir={str(sweep_dir)!r}",
            lambda df: df[column].isin(parents) if column in df else pd.Series(False, index=df.index),
        )
    ]


def _matching_runs(
    experiment_ids: list[str], steps: list[tuple[str, Any]], free: Any, uri: str
) -> pd.DataFrame:
    """The runs every step selects; when none, a `DataError` naming the first step that left no run."""
    try:
        runs = _search(experiment_ids, steps)
    except Exception as err:  # MlflowException for a malformed free filter string
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise DataError(f"report.filter={free!r}: MLflow rejected the filter ({first})") from None
    if runs.empty:
        for n in range(1, len(steps) + 1):
            if _search(experiment_ids, steps[:n]).empty:
                what = "no FINISHED job runs" if n == 1 else "matched no FINISHED job runs"
                raise DataError(f"{steps[n - 1][0]}: {what} in {uri}")
    return runs


def _keep_selected(runs: pd.DataFrame, report_cfg: Any) -> pd.DataFrame:
    """`runs` as `report.keep` says: all of them, or the latest per compared setting (`keep_latest`)."""
    keep = str(config_value(report_cfg, "keep", DEFAULT_KEEP))
    if keep not in KEEP_CHOICES:
        raise DataError(f"report.keep={keep!r}: expected one of {list(KEEP_CHOICES)}")
    if keep == "latest":
        axes = [str(a) for a in config_value(report_cfg, "axes", DEFAULT_AXES)]
        columns_by = config_value(report_cfg, "columns_by")
        runs = keep_latest(runs, [*axes, *([str(columns_by)] if columns_by else [])])
    return runs


def keep_latest(runs: pd.DataFrame, axes: Iterable[str]) -> pd.DataFrame:
    """The newest run (by start time; `runs` is sorted oldest first) per compared setting and seed: a
    stage rerun after a change replaces its older self instead of being averaged with it as a "seed"."""
    columns = [param_column(a) for a in [*axes, "seed"]]
    # A param no run logged is a column of None (`runs.get`), i.e. UNSET for every run: it splits nothing.
    keys = pd.DataFrame({c: runs.get(c) for c in columns}, index=runs.index)
    return runs[~keys.fillna(UNSET).astype(str).duplicated(keep="last")]


def differing_params(runs: pd.DataFrame, axes: Iterable[str]) -> list[str]:
    """Config keys (without `params.`) whose values differ across `runs`, other than the compared axes.

    Keys under a compared axis' config group are expected to differ with it (axis `model.name`: every
    `model.*` key) and are skipped, as are paths, outputs and the seed (`ignored_param`). A key some runs
    lack counts as differing when the others set it.
    """
    axis_keys = {param_column(a).removeprefix("params.") for a in axes}
    # A group choice (`model.name`) brings its whole group along; any other axis (`task.scene`) only itself.
    groups = tuple(k.removesuffix("name") for k in axis_keys if k.endswith(".name"))
    out = []
    for column in runs.columns:
        if not column.startswith("params."):
            continue
        key = column.removeprefix("params.")
        if key in axis_keys or ignored_param(key) or (groups and key.startswith(groups)):
            continue
        if runs[column].fillna(UNSET).astype(str).nunique() > 1:
            out.append(key)
    return sorted(out)


PER_IMAGE_ARTIFACT = "eval/per_image.csv"


def artifact_csv(run_id: str, artifact_path: str, dst: str) -> pd.DataFrame | None:
    """A run's CSV artifact read into a frame (downloaded under `dst`), or None, logged, when the run has
    none or the store cannot be reached."""
    try:
        local = mlflow.artifacts.download_artifacts(run_id=run_id, artifact_path=artifact_path, dst_path=dst)
    except (
        Exception
    ) as err:  # no such artifact (a search-only run, an older bench), or the store is unreachable
        log.info("report: run %s has no %s (%s)", run_id, artifact_path, err)
        return None
    return pd.read_csv(local)


#: The columns of `eval/per_image.csv` that name a scored item rather than score it: a denoiser's image
#: (scene, spp) and a radiance field's test view (view). Kept as they are, so items pair by name.
IMAGE_IDS = ("scene", "spp", "view")


def per_image_rows(runs: pd.DataFrame, required: str = "relmse_ratio") -> pd.DataFrame:
    """The rows of every run's `eval/per_image.csv` artifact that has column `required` (the denoising
    evaluations write `relmse_ratio`; NeRF's do not), each row extended with its run's columns (`params.*`,
    `run_id`) and its scores renamed `metrics.<score>`, so the report's tables can aggregate images as they
    aggregate runs. Runs without the artifact (or an unreachable store) are left out, logged."""
    import tempfile

    parts = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, (_, run) in enumerate(runs.iterrows()):
            images = artifact_csv(run["run_id"], PER_IMAGE_ARTIFACT, f"{tmp}/{i}")
            if images is None or required not in images:
                continue
            scores = images.rename(columns={c: f"metrics.{c}" for c in images if c not in IMAGE_IDS})
            context = {c: run[c] for c in runs.columns if c.startswith("params.") or c == "run_id"}
            parts.append(scores.assign(**context))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
