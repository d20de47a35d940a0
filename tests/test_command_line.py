"""Common mistakes on the command line, each one line (src/schema/command_line.py before Hydra starts;
src/schema/run.py::check_method_fits_task at job start and in stage=config), and the commands that must
still pass untouched."""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from src.errors import ConfigError
from src.schema.command_line import CONF_DIR, check_command_line, key_error, split_argv
from src.schema.run import check_method_fits_task, method_class, task_methods
from tests.conftest import ROOT, compose_config, one_line_cli_error, one_line_error

MODELS = sorted(p.stem for p in (CONF_DIR / "model").glob("*.yaml"))


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (
            ["model=kpcnn"],
            "model=kpcnn: no such model; did you mean kpcn or dpcn? (options: cross_bilateral,",
        ),
        (["dataset=volumetricc"], "dataset=volumetricc: no such dataset; did you mean volumetric?"),
        (["+sweep=denoisrs"], "sweep=denoisrs: no such sweep; did you mean denoisers?"),
        (
            ["-m", "seed=0,1", "model=kpcn,dpcnn"],
            "model=dpcnn: no such model; did you mean dpcn",
        ),  # a sweep list
        (["task.train.epoch=3"], "task.train.epoch: no such config key; did you mean task.train.epochs?"),
        (["train.epochs=3"], "train.epochs: no such config key; did you mean task.train.epochs?"),  # no group
        (
            ["metrics.lpip.enabled=false"],
            "metrics.lpip.enabled: no such config key; did you mean metrics.lpips",
        ),
        (["model=dpcn", "model.kernel_size=5"], "model.kernel_size: no such config key; keys under model: "),
        (["foo=1"], "foo: no such config key; keys under the root: auto_resume, compare,"),
        (["seed=[1,2"], "command line: "),  # a syntax error: Hydra's parser message, on one line
        (["model=kpcn,dpcn"], "model=kpcn,dpcn: a sweep runs one job per value only as a multirun; add -m"),
        (["seed=range(3)"], "seed=range(3): a sweep runs one job per value only as a multirun; add -m"),
        (["model=null"], "model=null: a config group takes one of its options: cross_bilateral, dpcn,"),
        (["-m", "model=null"], "model=null: a config group takes one of its options:"),
        (["+seed=3"], "+seed=3: seed is already in the config; set it without the +: seed=3"),
        (
            ["model=dpcn", "+model.conv_kernel=5"],  # the key exists once the model is chosen
            "+model.conv_kernel=5: model.conv_kernel is already in the config; set it without the +",
        ),
    ],
)
def test_each_mistake_is_one_line_with_the_nearest_names(argv, message):
    with pytest.raises(ConfigError) as excinfo:
        check_command_line(argv)
    text = str(excinfo.value)
    assert "\n" not in text
    if message is not None:
        assert text.startswith(message), text
    # never Hydra's "+key" advice
    assert "+" not in text.split(";")[0] or any(a.startswith("+") for a in argv)


@pytest.mark.parametrize(
    "argv",
    [
        [],
        ["--help"],
        ["task=nerf", "model=mipnerf", "task.scene=tabletop", "profile=smoke"],
        ["task.train.epochs=3", "dataset.noisy_spp=[4,8]", "metrics.lpips.enabled=false"],
        ["model=dpcn", "model.conv_kernel=3"],  # a key the chosen model has
        ["+task.train.new_key=1", "~seed"],  # additions and deletions are Hydra's and the schema's
        ["++seed=3", "++task.train.epochs=2", "++task.train.new_key=1"],  # ++ adds or overrides: Hydra's
        ["~hydra/job_logging"],  # a group deleted from the defaults: no value, and none is needed
        ["+model.new_key=1"],  # a + on a key that only another model has
        ["seed='0,1'"],  # a quoted value with a comma is one value, not a sweep
        ["hydra.run.dir=/tmp/somewhere", "hydra/launcher=basic"],
        ["-m", "+sweep=denoisers", "seed=0,1"],
        ["--cfg", "job", "stage=config"],
    ],
)
def test_commands_that_compose_pass_untouched(argv):
    check_command_line(argv)


def test_the_flags_are_not_overrides():
    assert split_argv(["-m", "--cfg", "job", "seed=1"]) == (["seed=1"], True, True)
    assert split_argv(["seed=1", "--help"]) == ([], False, False)  # nothing runs: nothing to check
    assert split_argv(["--config-dir", "mine", "seed=1"]) == ([], False, False)  # not conf/: stand aside


def test_a_users_own_config_folder_on_the_searchpath_adds_its_options():
    # docs/extending.md: a user's model YAML outside conf/ (tests/conf/model/toy.yaml)
    user = "hydra.searchpath=[file://tests/conf]"
    check_command_line(["model=toy", user])
    check_command_line(["-m", "model=dpcn,toy", user])
    with pytest.raises(ConfigError, match="model=toy: no such model"):
        check_command_line(["model=toy"])  # without the folder there is no such model
    check_command_line(["hydra/launcher=basic"])  # Hydra's own groups have Hydra's options
    with pytest.raises(ConfigError, match="hydra/launcher=basc: no such hydra/launcher; did you mean basic"):
        check_command_line(["hydra/launcher=basc"])


def test_a_key_error_names_the_deepest_part_that_exists():
    keys = ["task", "task.train", "task.train.epochs", "task.train.lr", "seed"]
    assert str(key_error("task.train.epoch", keys)).endswith("did you mean task.train.epochs?")
    assert str(key_error("task.trian.lr", keys)).endswith("did you mean task.train?")
    assert str(key_error("task.train.zz.y", keys)).endswith("keys under task.train: epochs, lr")
    assert str(key_error("train.lr", keys)).endswith("did you mean task.train.lr?")
    assert str(key_error("seed.x", keys)).endswith("seed has no keys")


# --- a model of another task ----------------------------------------------------------------------------

#: Written out by hand (not derived from the code it checks): which task runs each shipped model.
RADIANCE_FIELDS = {"nerf", "mipnerf", "refnerf"}
GP_FILTERS = {"gp_filter", "gp_expr1", "gp_expr2", "gp_expr3"}  # what the filter search evaluates
TASKS = {"denoise", "filter_search", "nerf"}


def test_every_model_is_of_one_kind_of_method_and_every_task_runs_one():
    assert set(task_methods()) == TASKS
    for model in MODELS:  # a new model file must say (by its class or builder) which methods it is
        target = compose_config([f"model={model}"]).model._target_
        assert method_class(str(target)) is not None, model


@pytest.mark.parametrize("model", MODELS)
@pytest.mark.parametrize("task", sorted(TASKS))
def test_a_model_runs_only_under_the_task_of_its_kind(model, task):
    from src.stages import task_of

    cfg = compose_config([f"task={task}", f"model={model}", "profile=smoke"])
    fits = {"nerf": model in RADIANCE_FIELDS, "filter_search": model in GP_FILTERS}.get(
        task, model not in RADIANCE_FIELDS
    )
    if fits:
        check_method_fits_task(cfg, task_of(cfg))
        return
    with pytest.raises(ConfigError) as excinfo:
        check_method_fits_task(cfg, task_of(cfg))
    add = (
        "add task=nerf"
        if model in RADIANCE_FIELDS
        else "add task=denoise or task=filter_search"
        if model in GP_FILTERS
        else "add task=denoise"
    )
    one_line_error(excinfo, f"model={model}: a ", f"the kind of method task={task} runs; {add}")


def _cli(args, cwd=ROOT):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}  # from another folder too
    return subprocess.run(
        [sys.executable, "-m", "src.run", *args],
        cwd=cwd,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_the_cli_rejects_a_mistake_in_one_line_with_status_2_and_leaves_no_folder(tmp_path):
    run_dir = tmp_path / "outputs" / "day" / "job"
    result = _cli(["task.train.epoch=3", f"hydra.run.dir={run_dir}"])
    one_line_cli_error(result, "task.train.epoch: no such config key; did you mean task.train.epochs?")
    assert not (tmp_path / "outputs").exists()
    # found at job start (the model's kind), also by stage=config: the folder Hydra made is removed again;
    # the folder above a given hydra.run.dir stays
    result = _cli(["profile=smoke", "model=nerf", "stage=config", f"hydra.run.dir={run_dir}"])
    one_line_cli_error(result, "model=nerf: a NeRF, not a Denoiser", "task=denoise runs; add task=nerf")
    assert not run_dir.exists() and run_dir.parent.is_dir()
    # Hydra's own outputs/<date>/<time>/: both go
    (tmp_path / "elsewhere").mkdir()
    result = _cli(["profile=smoke", "model=nerf", "stage=config"], cwd=tmp_path / "elsewhere")
    one_line_cli_error(result, "model=nerf: a NeRF, not a Denoiser")
    assert list((tmp_path / "elsewhere" / "outputs").iterdir()) == []


def test_a_rejected_job_keeps_a_folder_that_holds_more_than_hydras_files(tmp_path):
    run_dir = tmp_path / "job"
    run_dir.mkdir()
    (run_dir / "checkpoint.pt").write_text("a resumed job's")
    result = _cli(["profile=smoke", "model=nerf", "stage=config", f"hydra.run.dir={run_dir}"])
    assert result.returncode == 2 and (run_dir / "checkpoint.pt").is_file()
    assert Path(run_dir / ".hydra").is_dir()


def test_a_key_is_found_without_resolving_its_value():
    from omegaconf import OmegaConf

    from src.schema.command_line import has_key

    cfg = OmegaConf.create({"a": {"b": "${hydra:runtime.cwd}", "l": [1, {"x": 2}]}, "c": None})
    assert has_key(cfg, "a.b") and has_key(cfg, "a.l.1.x") and has_key(cfg, "c")
    assert not has_key(cfg, "a.z") and not has_key(cfg, "c.d") and not has_key(cfg, "a.b.c")
