"""Data kinds (`dataset._target_`, src/kinds/): every shipped dataset names a kind whose schema checks it,
a task refuses data of another family in one line, and a `_target_` that is no data kind is one line."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from src.errors import ConfigError
from tests.conftest import ROOT, compose_config, data_kind, one_line_error, smoke_config

#: Every dataset config under conf/dataset/, found by its file.
DATASET_CONFIGS = sorted(p.stem for p in (ROOT / "conf" / "dataset").glob("*.yaml"))
#: Kinds the configs must keep naming (a subset: a new config needs no line here).
KNOWN_KINDS = {
    "procedural": "src.kinds.stills.RenderedStills",
    "volumetric": "src.kinds.sequences.RenderedSequences",
    "noisebase": "src.kinds.noisebase.NoisebaseSequences",
    "nerf_procedural": "src.kinds.multiview.RenderedScenes",
    "blender": "src.kinds.multiview.BlenderScenes",
}


def _task_reading(name: str) -> str:
    """The task whose family of kinds the config's `_target_` belongs to (from the class, not a list)."""
    from src.kinds.base import kind_class
    from src.kinds.denoising import DenoisingKind

    dataset = OmegaConf.load(ROOT / "conf" / "dataset" / f"{name}.yaml")
    return "denoise" if issubclass(kind_class(dataset), DenoisingKind) else "nerf"


@pytest.mark.parametrize("name", DATASET_CONFIGS)
def test_every_dataset_config_names_a_data_kind(name):
    """Composed for the task that reads its family, each config builds its kind, whose schema names it."""
    from src.kinds.base import kind_class

    cfg = smoke_config("/tmp/unused", "/tmp/unused/run", [f"task={_task_reading(name)}", f"dataset={name}"])
    found = kind_class(cfg.dataset)
    assert found.schema is not None and found.schema.model_fields["name"].annotation.__args__ == (name,)
    if name in KNOWN_KINDS:
        assert f"{found.__module__}.{found.__name__}" == KNOWN_KINDS[name]


def test_the_known_kinds_are_found_by_the_glob():
    assert set(KNOWN_KINDS) <= set(DATASET_CONFIGS)
    assert {_task_reading(n) for n in ("procedural", "volumetric", "noisebase")} == {"denoise"}
    assert {_task_reading(n) for n in ("nerf_procedural", "blender")} == {"nerf"}


@pytest.mark.parametrize(
    ("task", "dataset", "needles"),
    [
        (
            "denoise",
            "nerf_procedural",
            ["dataset=nerf_procedural", "multi-view", "task=denoise", "denoising"],
        ),
        ("denoise", "blender", ["dataset=blender", "Blender-format", "task=denoise"]),
        ("nerf", "procedural", ["dataset=procedural", "still images", "task=nerf", "multi-view"]),
        ("nerf", "volumetric", ["dataset=volumetric", "image sequences", "task=nerf"]),
        ("filter_search", "nerf_procedural", ["dataset=nerf_procedural", "task=filter_search"]),
    ],
)
def test_a_task_refuses_data_of_another_family_in_one_line(tmp_path, task, dataset, needles):
    from src.schema.run import validate_run
    from src.stages import task_of

    cfg = smoke_config(tmp_path, tmp_path / "run", [f"task={task}"])
    cfg.dataset = smoke_config(tmp_path, tmp_path / "run", [f"dataset={dataset}"]).dataset
    if dataset == "blender":
        cfg.dataset.root = str(tmp_path)
    with pytest.raises(ConfigError) as excinfo:
        task_of(cfg)
    one_line_error(excinfo, *needles)
    with pytest.raises(ConfigError) as excinfo:
        validate_run(cfg)
    one_line_error(excinfo, *needles)


@pytest.mark.parametrize(
    ("target", "needles"),
    [
        (
            "src.tasks.denoise.DenoiseTask",
            ["dataset._target_", "src.tasks.denoise.DenoiseTask", "not a data kind"],
        ),
        ("src.kinds.nope.Kind", ["dataset._target_", "cannot import", "src.kinds.nope.Kind"]),
        (None, ["dataset._target_", "expected the dotted path"]),
    ],
)
def test_a_target_that_is_no_data_kind_is_one_line(tmp_path, target, needles):
    from src.stages import render

    cfg = smoke_config(tmp_path, tmp_path / "run")
    cfg.dataset._target_ = target
    with pytest.raises(ConfigError) as excinfo:
        render(cfg)
    one_line_error(excinfo, *needles)
    assert not (tmp_path / "procedural").exists()  # nothing rendered


def test_the_schema_of_the_kind_checks_the_dataset_group(tmp_path):
    """The dataset schema is the kind's: the volumetric kind's schema refuses a still-image key."""
    from src.schema.run import validate_run

    cfg = smoke_config(tmp_path, tmp_path / "run", ["dataset=volumetric", "+dataset.bases_extra=1"])
    with pytest.raises(ConfigError) as excinfo:
        validate_run(cfg)
    one_line_error(excinfo, "dataset.bases_extra")


#: Every denoiser config (conf/model/ but the radiance fields), found by its file.
DENOISERS = sorted(
    p.stem for p in (ROOT / "conf" / "model").glob("*.yaml") if "family: nerf" not in p.read_text()
)


@pytest.mark.parametrize("dataset", ["procedural", "volumetric"])
@pytest.mark.parametrize("model", DENOISERS)
def test_every_denoiser_runs_on_every_denoising_kind_that_has_its_inputs(tmp_path, model, dataset):
    """One batch contract: the KPCN family builds from the data's branches and input channels (two on
    still images, one over 62 channels on sequences), the filters read the shared buffers; the U-Net
    KPCN, which reads the sequences' radiance branch, is refused on still images in one line."""
    from src.schema.run import validate_run
    from src.tasks.denoise import DenoiseTask

    cfg = smoke_config(tmp_path, tmp_path / "run", [f"model={model}", f"dataset={dataset}"])
    values = validate_run(cfg)  # builds the model from the composed config
    if model in ("kpcn", "dpcn", "resnet"):
        branches = ["diffuse", "specular"] if dataset == "procedural" else ["radiance"]
        assert values["model"]["branches"] == branches
        assert values["model"]["in_channels"] == (28 if dataset == "procedural" else 62)
    if model == "unet_kpcn" and dataset == "procedural":
        with pytest.raises(ConfigError) as excinfo:
            DenoiseTask.for_run(cfg).check_stages(["train"], cfg)
        one_line_error(
            excinfo, "model=unet_kpcn", "radiance branch", "dataset=procedural", "diffuse, specular"
        )
    else:
        DenoiseTask.for_run(cfg).check_stages(["render", "preprocess", "train", "eval"], cfg)


def test_a_filter_whose_guides_the_sequences_lack_is_refused_at_job_start_in_one_line(tmp_path):
    """The GP expression reads the still images' variance guides; the prepared sequences' index says they
    are missing before any run is opened."""
    from src.tasks.denoise import DenoiseTask
    from tests.test_volume_shards import _preprocess, _raw

    _preprocess(_raw(tmp_path / "volumetric" / "raw"), tmp_path / "volumetric" / "prepared", patch_size=8)
    cfg = smoke_config(tmp_path, tmp_path / "run", ["model=gp_expr1", "dataset=volumetric"])
    cfg.paths.dataset = str(tmp_path / "volumetric")
    with pytest.raises(ConfigError) as excinfo:
        DenoiseTask.for_run(cfg).check_stages(["eval"], cfg)
    one_line_error(excinfo, "directIllumination", "visibility")
    # An expression of the buffers the sequences have (colour, normal, depth, albedo) passes the check.
    shared = "exp(-(distance2(depth, depth) + distance2(normal, normal) + distance2(color, color)))"
    merged = OmegaConf.merge(cfg, {"model": {"expression": shared}})
    DenoiseTask.for_run(merged).check_stages(["eval"], merged)


@pytest.mark.parametrize(
    ("dataset", "model", "line"),
    [
        ("procedural", "kpcn", None),
        ("volumetric", "unet_kpcn", "input features (dataset.volume_features, 62 channels)"),
        ("volumetric", "kpcn", "input features (dataset.volume_features, 62 channels)"),
    ],
)
def test_stage_summary_runs_on_every_denoising_kind(tmp_path, capsys, dataset, model, line):
    from src.stages import print_model_summary

    print_model_summary(smoke_config(tmp_path, tmp_path / "run", [f"model={model}", f"dataset={dataset}"]))
    out = capsys.readouterr().out
    assert "FLOPs per pixel" in out
    assert ("input features" not in out) if line is None else (line in out)


def test_the_benchmark_composes_a_model_with_the_data_whose_branches_it_reads():
    """`python -m src.bench denoise` times the U-Net KPCN with the sequences' 62 inputs (its data), the
    KPCN family with the default still images' 28 per branch."""
    from src.bench.model_configs import load_model_config

    assert load_model_config("unet_kpcn", "paper")["in_channels"] == 62
    kpcn = load_model_config("kpcn", "paper")
    assert kpcn["in_channels"] == 28 and kpcn["branches"] == ["diffuse", "specular"]


def test_the_benchmark_data_of_a_model_is_named_never_guessed(monkeypatch):
    """conf/compare.yaml's bench.data names the U-Net KPCN's data; a model it does not name, whose
    branches the default data lack, and an explicit dataset without them are one-line errors (issue 44:
    a new dataset, first in alphabetical order, once changed the U-Net KPCN's benchmarked inputs)."""
    from src.bench import model_configs

    assert compose_config().compare.bench.data == {"unet_kpcn": "volumetric"}
    with pytest.raises(ConfigError) as err:
        model_configs.load_model_config("unet_kpcn", "paper", dataset="procedural")
    one_line_error(err, "dataset=procedural", "radiance", "expected a dataset with those branches")
    real = model_configs._compose
    monkeypatch.setattr(
        model_configs, "_compose", lambda o, g, resolve=True: {} if g == "compare" else real(o, g, resolve)
    )
    with pytest.raises(ConfigError) as err:
        model_configs.load_model_config("unet_kpcn", "paper")
    one_line_error(err, "compare.bench.data.unet_kpcn: missing", "radiance", "procedural")


def test_a_checkpoint_trained_on_other_features_is_refused_in_one_line_by_each_kind(tmp_path):
    from src.errors import DataError

    sequences = data_kind(smoke_config(tmp_path, tmp_path / "run", ["dataset=volumetric"]))
    sequences.check_trained_features({"features": ["color", "albedo"]}, ["color", "albedo"], "a.pt")
    sequences.check_trained_features({}, ["color"], "a.pt")  # a checkpoint that records none
    with pytest.raises(DataError) as excinfo:
        sequences.check_trained_features({"features": None}, ["color", "albedo"], "a.pt")
    one_line_error(excinfo, "a.pt", "dataset.volume_features=None", "['color', 'albedo']")
    stills = data_kind(smoke_config(tmp_path, tmp_path / "run", ["dataset=procedural"]))
    stills.check_trained_features({"features": ["color", "normal"]}, ["color", "normal"], "b.pt")
    with pytest.raises(DataError) as excinfo:
        stills.check_trained_features({"features": ["color", "normal"]}, ["color", "depth"], "b.pt")
    one_line_error(excinfo, "b.pt", "task.features=[color,normal]", "[color,depth]")


class _Captured(Exception):
    """Raised by a stand-in sampler once it has the arguments a kind passed it (nothing is written)."""


#: Every preprocessing setting away from its default, shared (task.preprocess) and a kind's own.
SHARED_PREPROCESS = {
    "patch_size": 6,
    "candidates_factor": 3.0,
    "min_keep_prob": 0.2,
    "min_distance": 0.25,
    "importance": "mc_variance",
    "importance_window": 2.0,
    "importance_percentile": 90.0,
    "split_seed": 11,
    "sample_seed": 13,
    "whiten_eps": 1e-3,
}


def _captured_settings(tmp_path, monkeypatch, module, function, overrides):
    cfg = smoke_config(tmp_path / "data", tmp_path / "run", overrides)
    got = {}

    def sampler(*args, **kwargs):
        got.update(kwargs)
        raise _Captured

    monkeypatch.setattr(module, function, sampler)
    (tmp_path / "raw").mkdir()
    cfg.paths.raw = str(tmp_path / "raw")
    with pytest.raises(_Captured):
        data_kind(cfg).preprocess(cfg)
    return got


def test_every_still_image_preprocessing_setting_arrives_at_the_sampler(tmp_path, monkeypatch):
    import src.data.shards

    own = {"eps_albedo": 0.01, "specular_variance": "thesis", "patches_per_image": 7}
    overrides = [f"task.preprocess.{k}={v}" for k, v in SHARED_PREPROCESS.items()]
    overrides += [
        "task.preprocess.split_by_base=true",
        "task.preprocess.split={train:0.5,val:0.25,test:0.25}",
    ]
    overrides += [f"dataset.preprocess.{k}={v}" for k, v in own.items()]
    got = _captured_settings(tmp_path, monkeypatch, src.data.shards, "preprocess_dataset", overrides)
    want = {k: v for k, v in SHARED_PREPROCESS.items() if k != "min_distance"} | own
    want["eps"] = want.pop("eps_albedo")  # the sampler's name for it
    assert {k: got[k] for k in want} == want
    assert got["min_distance"] == 0.25 * 6  # in pixels: patch sizes x the patch size
    assert got["split_by_base"] is True and got["split_fractions"] == {
        "train": 0.5,
        "val": 0.25,
        "test": 0.25,
    }
    assert got["patches_per_split"] is None


def test_every_sequence_preprocessing_setting_arrives_at_the_sampler(tmp_path, monkeypatch):
    import src.data.volume_shards

    own = {"volume_transform": "none", "sequence_frames": 2, "patches_per_sequence": 5}
    overrides = ["dataset=volumetric", *(f"task.preprocess.{k}={v}" for k, v in SHARED_PREPROCESS.items())]
    overrides += ["task.preprocess.split_by_base=true", "dataset.second_reference=true"]
    overrides += [f"dataset.preprocess.{k}={v}" for k, v in own.items()]
    got = _captured_settings(
        tmp_path, monkeypatch, src.data.volume_shards, "preprocess_volume_dataset", overrides
    )
    want = {k: v for k, v in SHARED_PREPROCESS.items() if k != "min_distance"} | own
    assert {k: got[k] for k in want} == want
    assert got["min_distance"] == 0.25 * 6
    assert got["split_by_base"] is True and got["second_reference"] is True
