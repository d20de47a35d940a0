"""Data kinds (`dataset._target_`, src/kinds/): every shipped dataset names a kind whose schema checks it,
a task refuses data of another family in one line, and a `_target_` that is no data kind is one line."""

from __future__ import annotations

import pytest

from src.errors import ConfigError
from tests.conftest import ROOT, one_line_error, smoke_config

#: Each shipped dataset config, the kind it names, and the task that reads it.
SHIPPED = {
    "procedural": ("src.kinds.stills.RenderedStills", "denoise"),
    "volumetric": ("src.kinds.sequences.RenderedSequences", "denoise"),
    "nerf_procedural": ("src.kinds.multiview.RenderedScenes", "nerf"),
    "blender": ("src.kinds.multiview.BlenderScenes", "nerf"),
}


def test_every_dataset_config_names_a_data_kind():
    from src.kinds.base import kind_class

    configs = {p.stem for p in (ROOT / "conf" / "dataset").glob("*.yaml")}
    assert configs == set(SHIPPED)
    for name, (target, task) in SHIPPED.items():
        cfg = smoke_config("/tmp/unused", "/tmp/unused/run", [f"task={task}", f"dataset={name}"])
        found = kind_class(cfg.dataset)
        assert f"{found.__module__}.{found.__name__}" == target
        assert found.schema is not None and found.schema.model_fields["name"].annotation.__args__ == (name,)


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
        task_of(cfg).kind(cfg)
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
