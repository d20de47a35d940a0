"""The published GP filters that need world position (Davletaliyev 2016, Eqs. 4.2-4.8) run on our rendered
and preprocessed smoke data: directly on a test image, and (slow) through the evaluation stage; on data
that lack a buffer an expression reads, the job stops at start with one line."""

import json
import math
import subprocess

import pytest
import torch
from omegaconf import OmegaConf

from src.data.denoise_dataset import FullImageDataset
from src.errors import ConfigError
from src.gp.published import EXPR1, EXPR3
from src.models.filters.gp_filter import GPFilter
from src.models.instantiate import build_method
from src.stages import evaluate, task_of
from src.tracking.mlflow_tracking import job_run
from tests.conftest import ROOT, cli_job, one_line_cli_error, one_line_error, smoke_config

GP_KEYS = {"position", "position_var", "secondary_albedo", "secondary_albedo_var", "visibility"}


@pytest.mark.parametrize("model", ["gp_expr2", "gp_expr3"])
def test_gp_filters_needing_world_position_run_on_rendered_data(smoke_data, tmp_path, model):
    """The default `task.features` (no visibility) suffice: visibility and variances are batch keys."""
    cfg = smoke_config(smoke_data, tmp_path, ["tracking.enabled=false", f"model={model}", "model.radius=2"])
    item = FullImageDataset(cfg.paths.prepared, "test")[0]
    assert set(item) >= GP_KEYS and torch.linalg.vector_norm(item["position"], dim=0).max() > 0
    batch = {k: v[None] for k, v in item.items() if isinstance(v, torch.Tensor)}
    out = build_method(OmegaConf.to_container(cfg.model, resolve=True))(batch)["color"]
    assert out.shape == item["color"][None].shape and torch.isfinite(out).all()
    assert not torch.equal(out, batch["color"])


@pytest.mark.slow
@pytest.mark.parametrize("model", ["gp_expr2", "gp_expr3"])
def test_gp_filters_needing_world_position_evaluate_end_to_end(smoke_data, tmp_path, model):
    cfg = smoke_config(smoke_data, tmp_path, ["tracking.enabled=false", f"model={model}", "model.radius=2"])
    with job_run(cfg, run_name=model, tags={}) as tracker:
        summary = evaluate(cfg, tracker)
    assert summary["images"] == 2
    assert all(math.isfinite(v) for v in summary["mean"].values()), summary


def test_the_index_lists_every_tensor_key_of_an_item(smoke_data):
    """`FullImageDataset.batch_keys` (read from the index, what the job-start check trusts) is exactly
    what an item holds."""
    data = FullImageDataset(smoke_data / "procedural" / "smoke" / "prepared", "test")
    item = data[0]
    assert data.batch_keys == {k for k, v in item.items() if isinstance(v, torch.Tensor)}
    assert data.batch_keys >= GP_KEYS


def _data_without_world_position(smoke_data, tmp_path):
    """A data dir whose prepared test index lacks the world position (as real KPCN data do); the shards
    are not copied: the check must fail from the index alone."""
    index = json.loads((smoke_data / "procedural/smoke/prepared/full/test/index.json").read_text())
    del index["channels"]["position"], index["channels"]["position_var"]
    out = tmp_path / "data" / "procedural/smoke/prepared/full/test/index.json"
    out.parent.mkdir(parents=True)
    out.write_text(json.dumps(index))
    return tmp_path / "data"


def test_a_gp_filter_needing_a_buffer_the_data_lack_stops_at_job_start(smoke_data, tmp_path):
    data = _data_without_world_position(smoke_data, tmp_path)
    cfg = smoke_config(data, tmp_path / "run", ["model=gp_expr2", "stage=eval"])
    with pytest.raises(ConfigError) as excinfo:
        task_of(cfg).check_stages(["eval"], cfg)
    one_line_error(excinfo, "model.expression", "'worldPosition'", "'position'", "stage=render")
    for model in ("gp_expr1", "cross_bilateral"):  # they read no world position
        cfg = smoke_config(data, tmp_path / "run", [f"model={model}", "stage=eval"])
        task_of(cfg).check_stages(["eval"], cfg)


def test_gp_filter_checks_keys_as_it_reads_them():
    """`check_batch_keys` accepts what `features` can read (visibility from the network inputs too) and
    names the first buffer it cannot."""
    keys = {"color", "normal", "albedo", "depth", "visibility"}
    GPFilter(EXPR1, radius=1).check_batch_keys(keys)
    via_inputs = GPFilter(EXPR1, radius=1, input_features=["color", "visibility"])
    via_inputs.check_batch_keys((keys - {"visibility"}) | {"diffuse_in"})
    with pytest.raises(ConfigError) as excinfo:
        via_inputs.check_batch_keys(keys - {"visibility"})  # no diffuse_in to read it from
    one_line_error(excinfo, "'directIllumination'", "'visibility'")
    with pytest.raises(ConfigError) as excinfo:
        GPFilter(EXPR3, radius=1).check_batch_keys(keys | {"position"})
    one_line_error(excinfo, "'wpVariance'", "'position_var'")


@pytest.mark.slow
def test_a_gp_filter_needing_a_buffer_the_data_lack_is_one_line_through_the_cli(smoke_data, tmp_path):
    data = _data_without_world_position(smoke_data, tmp_path)
    cmd, env = cli_job(
        ["stage=eval", "profile=smoke", "model=gp_expr2", f"hydra.run.dir={tmp_path}/run"], data
    )
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    one_line_cli_error(result, "'worldPosition'", "'position'")
    assert not (tmp_path / "run" / "eval").exists() and not (data / "mlflow.db").exists()
