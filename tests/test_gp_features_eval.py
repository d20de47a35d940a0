"""The published GP filters that need world position (Davletaliyev 2016, Eqs. 4.2-4.8) run on our rendered
and preprocessed smoke data: directly on a test image, and (slow) through the evaluation stage."""

import math

import pytest
import torch
from omegaconf import OmegaConf

from src.data.denoise_dataset import FullImageDataset
from src.models.instantiate import build_method
from src.stages import evaluate
from src.tracking.mlflow_tracking import job_run
from tests.conftest import smoke_config

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
