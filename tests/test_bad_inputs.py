"""Bad config values and stages started too early: one line naming the key (or file), the value found and
what is expected; exit status 2 and no traceback through the real CLI. Every row of the table is checked
in-process (fast); a sample goes through `python -m src.run`, the whole table with `-m slow`."""

import os
import subprocess
import sys

import pytest

from src.errors import ConfigError, DataError
from src.schema.run import validate_run
from src.stages import stages_to_run, task_of
from tests.conftest import ROOT, one_line_cli_error, one_line_error, smoke_config

#: (overrides, what the one line must contain)
BAD_VALUES = [
    (["task=nerf", "dataset=procedural"], ["dataset=procedural: still images", "task=nerf reads multi-view"]),
    (["dataset=nerf_procedural"], ["dataset=nerf_procedural", "task=denoise reads denoising data"]),
    (["dataset._target_=src.tasks.nerf.NerfTask"], ["dataset._target_", "not a data kind"]),
    (["task.train.batch_size=-4"], ["task.train.batch_size=-4: expected a positive integer"]),
    (["task.train.lr=abc"], ["task.train.lr='abc': expected a number"]),
    (["task.train.lr=0"], ["task.train.lr=0: expected a positive number"]),
    (["+task.train.batchsize=4"], ["task.train.batchsize: unknown key", "'batch_size'"]),
    (["task.train.amp=1"], ["task.train.amp=1: expected true or false"]),
    (["task.train.max_steps=0"], ["task.train.max_steps=0: expected a positive integer"]),
    (["task.train.epochs=2.5"], ["task.train.epochs=2.5: expected an integer"]),
    (["task.train.loss=l3"], ["task.train.loss='l3'", "'smape'"]),
    (["task.preprocess.split.val=0.5"], ["task.preprocess.split: fractions sum to 1.35; expected 1"]),
    (["task.preprocess.min_keep_prob=1.5"], ["task.preprocess.min_keep_prob=1.5: expected a value <= 1"]),
    (
        ["dataset.preprocess.specular_variance=exact"],
        ["dataset.preprocess.specular_variance='exact'", "'thesis'"],
    ),
    (["task.preprocess.importance=bako"], ["task.preprocess.importance='bako'", "'mc_variance'"]),
    (
        ["task.preprocess.importance_window=0"],
        ["task.preprocess.importance_window=0: expected a positive number"],
    ),
    (["task.preprocess.repair.negative=drop"], ["task.preprocess.repair.negative='drop'", "'clamp'"]),
    (["task.features=[color,colour]"], ["task.features[1]='colour'", ".var or .grad"]),
    (["task.eval.split=train"], ["task.eval.split='train': expected one of 'val' or 'test'"]),
    (["task.eval.tile=-1"], ["task.eval.tile=-1: expected a non-negative integer"]),
    (["device=gpu"], ["device='gpu': expected one of 'auto', 'cpu' or 'cuda'"]),
    (["seed=-1"], ["seed=-1: expected a non-negative integer"]),
    (["metrics.tonemap=aces"], ["metrics.tonemap='aces'", "'clip_gamma'"]),
    (["metrics.ssim.win_size=0"], ["metrics.ssim.win_size=0: expected a positive integer"]),
    (["metrics.protocol=nppd"], ["metrics.protocol='nppd'", "'noisebase'"]),
    (["metrics.noisebase.warmup=-1"], ["metrics.noisebase.warmup=-1: expected a non-negative integer"]),
    (["render.variant=vulkan"], ["render.variant='vulkan'", "'llvm_ad_rgb'"]),
    (["tracking.experiment="], ["tracking.experiment=''", "non-empty"]),
    (["+foo=1"], ["foo: unknown key"]),
    (["model.width=-3"], ["model.width", "-3"]),
    (["+model.widht=3"], ["model.widht: not an argument of conv_stack_denoiser"]),
    (["model=kpcn", "model.kernel_size=4"], ["model.kernel_size", "odd"]),
    (["task=nerf", "task.train.val_every=0"], ["task.train.val_every=0: expected a positive integer"]),
    (["task=nerf", "task.train.precrop_frac=1.5"], ["task.train.precrop_frac=1.5: expected a value <= 1"]),
    (["task=nerf", "task.train.micro_batch_rays=0"], ["task.train.micro_batch_rays=0: expected a positive"]),
    (
        ["task=nerf", "task.train.cpu_micro_batch_rays=0"],
        ["task.train.cpu_micro_batch_rays=0: expected a positive"],
    ),
    (["task=nerf", "task.train.batching=one_image"], ["task.train.batching='one_image'", "'single_image'"]),
    (["task=nerf", "model.opaque_background=maybe"], ["model.opaque_background", "maybe"]),
    (["task=nerf", "task.eval.split=train"], ["task.eval.split='train'"]),
    (["task=nerf", "model.num_coarse_samples=0"], ["model.num_coarse_samples", "0"]),
    (["dataset.width=0"], ["dataset.width=0: expected a positive integer"]),
    (
        ["dataset.integrator.albedo_samples=0"],
        ["dataset.integrator.albedo_samples=0: expected a positive integer"],
    ),
    (
        ["dataset.reference_spp=16"],
        ["dataset.reference_spp=16: expected more than the largest noisy_spp (16)"],
    ),
    (["dataset.randomize.fov=[60,30]"], ["dataset.randomize.fov=[60, 30]: expected [lo, hi] with lo <= hi"]),
    (["dataset.randomize.materials=[wood]"], ["dataset.randomize.materials[0]='wood'", "'plastic'"]),
    (["dataset.noisy_spp=[]"], ["dataset.noisy_spp=[]: expected a non-empty list"]),
    (["dataset.noisy_spp=[1,16]"], ["dataset.noisy_spp=[1, 16]: expected sample counts >= 2"]),
    (["task=nerf", "dataset.far=1.0"], ["dataset.far=1: expected more than dataset.near=2"]),
    (["task=nerf", "dataset.views.train=0"], ["dataset.views.train=0: expected a positive integer"]),
    (["task=nerf", "dataset=blender"], ["dataset.root='???': missing; expected the folder"]),
    (
        ["dataset.base_scenes.tabletop.light.radiance=-1"],
        ["dataset.base_scenes.tabletop.light.radiance=-1: expected a non-negative number"],
    ),
    (
        ["+dataset.base_scenes.cornell.lights=2"],
        ["dataset.base_scenes.cornell.lights: unknown key", "'camera'"],
    ),
    (
        ["task=nerf", "dataset.scene_params.busy.shapes=[torus]"],
        ["dataset.scene_params.busy.shapes[0]='torus'"],
    ),
    (["task=nerf", "dataset.scene_params.spheres.env.res=0"], ["spheres.env.res=0: expected a positive"]),
    (["dataset=volumetric", "dataset.frames=0"], ["dataset.frames=0: expected a positive integer"]),
    (
        ["dataset=volumetric", "dataset.base_scenes.cloud.medium.g=[0.5,1.5]"],
        ["dataset.base_scenes.cloud.medium.g=[0.5, 1.5]: expected Henyey-Greenstein g in [-0.99, 0.99]"],
    ),
    (["dataset=volumetric", "dataset.bases=[volcano]"], ["dataset.bases[0]='volcano'", "'godrays'"]),
    (
        ["dataset.preprocess.patches_per_split={train: 0, val: 3}"],
        ["patches_per_split.train=0: expected a positive"],
    ),
    (
        ["task=nerf", "profile_tasks=[denoise]"],
        ["profile=smoke: has sizes for task ['denoise'], not task=nerf"],
    ),
    (
        ["dataset=volumetric", "dataset.preprocess.volume_transform=log"],
        ["dataset.preprocess.volume_transform='log'", "'log_modulus'"],
    ),
    (
        ["dataset=volumetric", "dataset.preprocess.sequence_frames=0"],
        ["dataset.preprocess.sequence_frames=0: expected a positive integer"],
    ),
    (
        ["dataset=volumetric", "dataset.preprocess.patches_per_sequence=-1"],
        ["dataset.preprocess.patches_per_sequence=-1: expected a positive integer"],
    ),
    (
        ["dataset=volumetric", "dataset.volume_features=[color,position]"],
        ["dataset.volume_features[1]='position'", "optionally with .var"],
    ),
    (
        ["task=filter_search", "task.search.crossover=0.5"],
        ["task.search: replication + crossover + mutation = 1.05; expected 1"],
    ),
    (["task=filter_search", "task.search.split=test"], ["task.search.split='test' is task.eval.split"]),
    (["task=filter_search", "+task.search.mutation_kinds.grow=1.0"], ["task.search.mutation_kinds", "grow"]),
    (
        ["task=filter_search", "task.search.tournament_size=0"],
        ["task.search.tournament_size=0: expected a positive integer"],
    ),
    (["task=filter_search", "task.search.migrants=4"], ["task.search.migrants=4: expected fewer than"]),
    (
        ["task=filter_search", "task.search.vector_pairs=both"],
        ["task.search.vector_pairs='both'", "'mixed'", "'same'"],
    ),
    (
        ["task=filter_search", "task.search.crossover_points=uniform"],
        ["task.search.crossover_points='uniform'", "'type_first'", "'thesis'"],
    ),
    (
        ["task=filter_search", "task.search.shares_count=children"],
        ["task.search.shares_count='children'", "'draws'", "'individuals'"],
    ),
    (
        ["task=filter_search", "task.search.max_constants=4"],
        ["task.search.max_constants=4: the seed", "has 10 constants; expected at least that many"],
    ),
    (["task=filter_search", "task.search.hall_of_fame=-1"], ["task.search.hall_of_fame=-1"]),
    (["task=filter_search", "task.search.fitness_cache=maybe"], ["task.search.fitness_cache='maybe'"]),
    (["model=unet_kpcn", "model.widths=[]"], ["model.widths", "non-empty list"]),
    (["model=unet_kpcn", "model.components=diffuse"], ["model.components", "surface_volume"]),
    (["model=unet_kpcn", "model.filter_space=log"], ["model.filter_space", "'transformed'"]),
    # A user's Blender scenes come at their own size: no profile gives them one, and none is accepted.
    (
        ["task=nerf", "dataset=blender", "dataset.root=/x", "+dataset.width=100"],
        ["dataset.width: unknown key", "'downscale'"],
    ),
    (
        ["dataset=volumetric", "dataset.feature_selection.subsets=bernoulli"],
        ["dataset.feature_selection.subsets='bernoulli'", "'uniform_size'", "'independent'"],
    ),
]
#: Run through the real CLI in the default suite (the rest with `-m slow`).
CLI_SAMPLE = {0, 11}


@pytest.mark.parametrize(("overrides", "needles"), BAD_VALUES, ids=lambda v: " ".join(v) if v else "")
def test_a_bad_config_value_is_one_line_before_anything_runs(overrides, needles, tmp_path):
    cfg = smoke_config(tmp_path / "data", tmp_path / "run", overrides)
    with pytest.raises(ConfigError) as excinfo:
        validate_run(cfg)
    one_line_error(excinfo, *needles)


def test_the_shipped_configs_pass_the_schema(tmp_path):
    shipped = (
        [],
        ["profile=paper"],
        ["profile=bako"],
        ["task=nerf"],
        ["task=nerf", "profile=paper", "model=refnerf"],
        ["dataset=volumetric"],
        [
            "dataset=volumetric",
            "profile=cpu",
            "dataset.render_scenes=[cloud-0000]",
            "dataset.render_frames=[0,1]",
        ],
        ["dataset=volumetric", "profile=paper"],
        ["dataset=volumetric", "model=unet_kpcn"],
        ["dataset=volumetric", "model=resnet", "profile=paper"],
        ["task=filter_search"],
        ["task=filter_search", "profile=paper"],
    )
    for overrides in (*shipped, ["task=nerf", "dataset=blender", f"dataset.root={tmp_path}"]):
        cfg = smoke_config(tmp_path / "data", tmp_path / "run", overrides)
        validate_run(cfg)
        task_of(cfg).check_stages(stages_to_run(cfg), cfg)


def run_cli(args, data):
    env = {**os.environ, "NRBENCH_DATA_DIR": str(data), "MLFLOW_TRACKING_URI": f"sqlite:///{data}/mlflow.db"}
    cmd = [sys.executable, "-m", "src.run", *args, f"hydra.run.dir={data}/run", "profile=smoke"]
    return subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)


def _cli_cases(slow: bool):
    marks = [pytest.mark.slow] if slow else []
    return [
        pytest.param(o, n, marks=marks, id=" ".join(o))
        for i, (o, n) in enumerate(BAD_VALUES)
        if (i in CLI_SAMPLE) != slow
    ]


@pytest.mark.parametrize(("overrides", "needles"), _cli_cases(slow=False) + _cli_cases(slow=True))
def test_the_cli_exits_2_with_the_line_and_writes_nothing(overrides, needles, tmp_path):
    data = tmp_path / "data"
    result = run_cli(overrides, data)
    one_line_cli_error(result, *needles)
    assert not (data / "procedural").exists() and not (data / "nerf_procedural").exists()


@pytest.mark.parametrize(
    ("args", "needles"),
    [
        (["stage=train"], ["prepared/patches/train/index.json", "run stage=preprocess (or dvc repro) first"]),
        pytest.param(["stage=preprocess"], ["raw: not found", "run stage=render"], marks=pytest.mark.slow),
        pytest.param(["stage=eval"], ["run stage=preprocess"], marks=pytest.mark.slow),
        pytest.param(
            ["task=nerf", "stage=train"],
            ["transforms_train.json", "run stage=render"],
            marks=pytest.mark.slow,
        ),
    ],
)
def test_a_stage_started_too_early_names_the_stage_to_run_first(args, needles, tmp_path):
    one_line_cli_error(run_cli(args, tmp_path / "data"), *needles)


def _garbage_exr(data):
    raw = data / "procedural" / "smoke" / "raw"
    raw.mkdir(parents=True)
    for scene in ("box", "room", "sky"):  # three scenes: enough to split into train/val/test
        for spp in (4, 128):
            (raw / f"{scene}-{spp:05d}spp.exr").write_bytes(b"not an EXR")
    return ["stage=preprocess"], ["-00128spp.exr", "EXR"]


def _malformed_transforms(data):
    scene = data / "nerf_procedural" / "smoke" / "scenes" / "spheres"
    scene.mkdir(parents=True)
    (scene / "transforms_train.json").write_text('{"camera_angle_x": 0.69, "frames": [')
    return ["task=nerf", "stage=train"], [str(scene / "transforms_train.json"), "JSON"]


def _garbage_checkpoint(data):
    scene = data / "nerf_procedural" / "smoke" / "scenes" / "spheres"
    scene.mkdir(parents=True)
    (scene / "transforms_test.json").write_text('{"camera_angle_x": 0.69, "frames": []}')
    (data / "final.pt").write_bytes(b"\x00garbage")
    return ["task=nerf", "stage=eval", f"task.eval.checkpoint={data}/final.pt"], [
        "final.pt",
        "not a readable",
    ]


@pytest.mark.parametrize(
    "make",
    # all slow: tests/test_run.py already runs a bad EXR through the CLI in the default suite
    [
        pytest.param(f, marks=pytest.mark.slow)
        for f in (_garbage_exr, _malformed_transforms, _garbage_checkpoint)
    ],
)
def test_bad_data_is_one_line_through_the_cli(make, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    args, needles = make(data)
    one_line_cli_error(run_cli(args, data), *needles)


@pytest.mark.parametrize(
    ("task", "made"), [("denoise", "procedural/smoke/prepared/full/test/index.json"), ("nerf", None)]
)
def test_a_learned_methods_evaluation_needs_its_checkpoint_whatever_the_task(task, made, tmp_path):
    """`stages.require_inputs` adds the checkpoint of a learned method to what the task's eval reads."""
    from src.stages import require_inputs, task_of

    models = {"denoise": ("kpcn", "oidn"), "nerf": ("mipnerf", None)}[task]
    overrides = [f"task={task}"]
    cfg = smoke_config(tmp_path / "data", tmp_path / "run", [*overrides, f"model={models[0]}"])
    made = made or f"nerf_procedural/smoke/scenes/{cfg.task.scene}/transforms_test.json"
    (tmp_path / "data" / made).parent.mkdir(parents=True)
    (tmp_path / "data" / made).touch()
    with pytest.raises(DataError) as excinfo:
        require_inputs(task_of(cfg), "eval", cfg)
    one_line_error(excinfo, str(tmp_path / "run" / "checkpoints" / "final.pt"), "run stage=train")
    if models[1] is not None:  # a filter is evaluated without one
        cfg = smoke_config(tmp_path / "data", tmp_path / "run", [*overrides, f"model={models[1]}"])
        require_inputs(task_of(cfg), "eval", cfg)
