"""A Hydra sweeper that searches hyperparameters with Optuna's ask-and-tell API.

Why not the registry's `hydra-optuna-sweeper`: its last release pins optuna < 3 (2.10, from 2021), which
predates the current `ask(fixed_distributions)` API and the samplers' fixes, and would hold the whole
environment to it. This plugin is the small part we need on the current Optuna: it turns Hydra's sweep
syntax (`choice(...)`, `range(...)`, `interval(...)`, `tag(log, interval(...))`, `a,b,c`) into Optuna
distributions, asks the sampler for a batch of trials, runs them through the configured launcher (so the
local parallel and SLURM launchers work unchanged), and tells Optuna each job's objective: a value the
job returns (`python -m src.run` returns each stage's summary, e.g. `train.val_loss_color`).

Hydra only instantiates plugins from the `hydra_plugins` namespace package, hence this location; the
config is `conf/hydra/sweeper/optuna.yaml`.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import (
    ChoiceSweep,
    IntervalSweep,
    Override,
    RangeSweep,
)
from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf

from src.errors import ConfigError

if TYPE_CHECKING:
    import optuna

log = logging.getLogger("nrbench.optuna")

RESULTS_FILE = "optuna_trials.csv"
BEST_FILE = "optuna_best.yaml"
SAMPLERS = ("tpe", "random")


def distribution(override: Override) -> optuna.distributions.BaseDistribution:
    """The Optuna distribution of one sweep override: `choice`/`a,b` -> categorical, `range` -> int with
    step, `interval` -> float (int when both ends are ints), log-scaled when tagged `log`."""
    import optuna  # here, not at module level: Hydra imports every plugin module at each start

    sweep = override.value()
    key = override.get_key_element()
    if isinstance(sweep, ChoiceSweep):
        return optuna.distributions.CategoricalDistribution(list(sweep.list))
    if isinstance(sweep, RangeSweep):
        if not all(isinstance(v, int) for v in (sweep.start, sweep.stop, sweep.step)):
            raise ConfigError(f"{key}: range() of non-integers; use interval() for a float range")
        return optuna.distributions.IntDistribution(int(sweep.start), int(sweep.stop) - 1, step=sweep.step)
    if isinstance(sweep, IntervalSweep):
        log_scale = "log" in sweep.tags
        if isinstance(sweep.start, int) and isinstance(sweep.end, int):
            return optuna.distributions.IntDistribution(sweep.start, sweep.end, log=log_scale)
        return optuna.distributions.FloatDistribution(float(sweep.start), float(sweep.end), log=log_scale)
    raise ConfigError(f"{key}: {type(sweep).__name__} sweeps are not supported by the Optuna sweeper")


def search_space(overrides: Sequence[str]) -> tuple[dict[str, Any], list[str]]:
    """Split overrides into the searched distributions (by key) and the fixed overrides every trial gets.
    A later override of the same key wins (the command line after the sweep file's `params`)."""
    distributions: dict[str, Any] = {}
    fixed: dict[str, str] = {}
    for override in OverridesParser.create().parse_overrides(list(overrides)):
        key = override.get_key_element()
        distributions.pop(key, None)
        fixed.pop(key, None)
        if override.is_sweep_override():
            distributions[key] = distribution(override)
        else:
            fixed[key] = override.input_line
    return distributions, list(fixed.values())


def objective_value(returned: Any, path: str) -> float:
    """The number at dotted `path` in a job's return value (nested mappings); NaN/inf is an error."""
    node = returned
    for part in path.split("."):
        if not isinstance(node, Mapping) or part not in node:
            found = sorted(node) if isinstance(node, Mapping) else type(node).__name__
            raise ConfigError(
                f"hydra.sweeper.objective={path}: no '{part}' in the job's result (found {found})"
            )
        node = node[part]
    value = float(node)
    if not math.isfinite(value):
        raise ConfigError(f"hydra.sweeper.objective={path}: the job returned {value}")
    return value


def _as_override(key: str, value: Any) -> str:
    return f"{key}={value!r}" if isinstance(value, float) else f"{key}={value}"


class OptunaSweeper(Sweeper):
    """`hydra/sweeper=optuna`: `n_trials` trials in batches of `n_jobs`, objective read from each job."""

    def __init__(
        self,
        objective: str,
        direction: str,
        n_trials: int,
        n_jobs: int,
        seed: int | None,
        sampler: str,
        params: Mapping[str, str] | None = None,
    ) -> None:
        if direction not in ("minimize", "maximize"):
            raise ConfigError(f"hydra.sweeper.direction={direction}: expected minimize or maximize")
        if sampler not in SAMPLERS:
            raise ConfigError(f"hydra.sweeper.sampler={sampler}: expected one of {sorted(SAMPLERS)}")
        if n_trials < 1 or n_jobs < 1:
            raise ConfigError(f"hydra.sweeper: n_trials={n_trials}, n_jobs={n_jobs}; both must be >= 1")
        self.objective = objective
        self.direction = direction
        self.n_trials = n_trials
        self.n_jobs = n_jobs
        self.seed = seed
        self.sampler = sampler
        self.params = {str(k): str(v) for k, v in (params or {}).items()}
        self.hydra_context: HydraContext | None = None
        self.config: DictConfig | None = None
        self.launcher = None
        self.sweep_dir: Path | None = None

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction, config: DictConfig) -> None:
        self.hydra_context = hydra_context  # read by Sweeper.validate_batch_is_legal
        self.config = config
        self.launcher = Plugins.instance().instantiate_launcher(
            hydra_context=hydra_context, task_function=task_function, config=config
        )
        from src.multirun import sweep_dir

        self.sweep_dir = sweep_dir(config)  # relative to the launch dir, as the sweep callback resolves it

    def _study(self) -> optuna.Study:
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)  # one line per trial is ours to print
        samplers = {"tpe": optuna.samplers.TPESampler, "random": optuna.samplers.RandomSampler}
        return optuna.create_study(direction=self.direction, sampler=samplers[self.sampler](seed=self.seed))

    def sweep(self, arguments: list[str]) -> list[Any]:
        params = [f"{k}={v}" for k, v in self.params.items()]
        distributions, fixed = search_space([*params, *arguments])
        if not distributions:
            raise ConfigError("hydra.sweeper.params: nothing to search (no sweep override given)")
        study = self._study()
        log.info("Optuna %s of %s over %s", self.direction, self.objective, ", ".join(distributions))
        returns: list[Any] = []
        while len(returns) < self.n_trials:
            trials = [study.ask(distributions) for _ in range(min(self.n_jobs, self.n_trials - len(returns)))]
            batch = [fixed + [_as_override(k, v) for k, v in t.params.items()] for t in trials]
            self.validate_batch_is_legal(batch)
            results = self.launcher.launch(batch, initial_job_idx=len(returns))
            for trial, result in zip(trials, results, strict=True):
                self._tell(study, trial, result)
            returns.extend(results)
        self._write_results(study)
        return [returns]

    def _tell(self, study: optuna.Study, trial: optuna.Trial, result: Any) -> None:
        from optuna.trial import TrialState

        try:
            value = objective_value(result.return_value, self.objective)  # re-raises a failed job's error
        except Exception as err:  # a failed trial is recorded and the search goes on
            log.warning("trial %d failed: %s", trial.number, err)
            study.tell(trial, state=TrialState.FAIL)
            return
        study.tell(trial, value)
        log.info("trial %d: %s = %.6g with %s", trial.number, self.objective, value, trial.params)

    def _write_results(self, study: optuna.Study) -> None:
        from optuna.trial import TrialState

        from src.io.atomic import atomic_write_text

        frame = study.trials_dataframe(attrs=("number", "value", "params", "state"))
        atomic_write_text(self.sweep_dir / RESULTS_FILE, frame.to_csv(index=False))
        complete = [t for t in study.trials if t.state == TrialState.COMPLETE]
        if not complete:
            log.error("Optuna: no trial completed; see %s", self.sweep_dir / RESULTS_FILE)
            return
        best = study.best_trial
        print(
            f"optuna: best {self.objective} = {best.value:.6g} with "
            f"{' '.join(_as_override(k, v) for k, v in best.params.items())} "
            f"({len(complete)}/{len(study.trials)} trials complete) -> {self.sweep_dir / RESULTS_FILE}",
            flush=True,
        )
        best_record = {
            "objective": self.objective,
            "direction": self.direction,
            "value": best.value,
            "params": best.params,
        }
        atomic_write_text(self.sweep_dir / BEST_FILE, OmegaConf.to_yaml(OmegaConf.create(best_record)))
