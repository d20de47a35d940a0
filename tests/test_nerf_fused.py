"""The fused MLP path (`fields.SkipMLP`: split matmuls instead of concatenations, per-ray view pieces,
in-place ReLU) computes the same function as the straightforward cat / nn.Linear / ReLU form: the
outputs and every parameter's gradient of each model's loss agree within fp32 rounding."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from src.models.instantiate import build_method
from src.models.nerf.fields import SkipMLP
from tests.conftest import compose_config

NAMES = ("nerf", "mipnerf", "refnerf")


pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py


def plain_forward(self: SkipMLP, *pieces: torch.Tensor) -> torch.Tensor:
    """The straightforward SkipMLP: the pieces concatenated (per-ray ones expanded over the samples),
    then nn.Linear, ReLU and a torch.cat at every skip."""
    lead = torch.broadcast_shapes(*(p.shape[:-1] for p in pieces))
    x = torch.cat([p.expand(*lead, p.shape[-1]) for p in pieces], dim=-1)
    h = x
    for i, layer in enumerate(self.layers):
        h = F.relu(layer(h))
        if self._skip_after(i):
            h = torch.cat([h, x], dim=-1)
    return h


def small_paper_layout(name: str):
    """The paper's layout (depth 8, skip after layer 4; Ref-NeRF's 8-layer directional MLP) at width 32
    and 8 + 8 samples, so that the check is quick but covers every skip."""
    overrides = [
        f"model={name}",
        "profile=paper",
        "model.width=32",
        "model.bottleneck_width=16",
        "model.view_width=16",
        "model.num_coarse_samples=8",
        "model.num_fine_samples=8",
    ]
    if name == "refnerf":
        overrides += ["model.orientation_loss_mult=0.5", "model.pred_normal_loss_mult=0.1"]
    cfg = OmegaConf.to_container(compose_config(overrides).model, resolve=True)
    torch.manual_seed(0)
    return build_method(cfg)


def rays(n: int = 12, seed: int = 0, dtype=torch.float32) -> dict[str, torch.Tensor]:
    gen = torch.Generator().manual_seed(seed)
    origins = F.normalize(torch.randn(n, 3, generator=gen), dim=-1) * 4
    directions = -origins / 4 + 0.2 * torch.randn(n, 3, generator=gen)
    batch = {
        "origins": origins,
        "directions": directions,
        "viewdirs": F.normalize(directions, dim=-1),
        "radii": torch.full((n, 1), 0.01),
        "near": torch.full((n, 1), 2.0),
        "far": torch.full((n, 1), 6.0),
        "rgb": torch.rand(n, 3, generator=gen),
    }
    return {k: v.to(dtype) for k, v in batch.items()}


def loss_and_grads(model, batch):
    model.zero_grad(set_to_none=True)
    noise = model.draw_noise(len(batch["rgb"]), batch["near"], torch.Generator().manual_seed(3))
    outputs = model(batch, randomized=True, noise=noise)
    loss, _ = model.loss(outputs, batch["rgb"])
    loss.backward()
    grads = {k: p.grad.clone() for k, p in model.named_parameters()}
    return outputs, loss.detach(), grads


def fields_and_grads(model, batch):
    """Every level's field on fixed intervals (fp32), and the parameters' gradients of a sum of them."""
    model.zero_grad(set_to_none=True)
    n, s = len(batch["rgb"]), model.num_coarse_samples
    tdist = torch.linspace(2.0, 6.0, s + 1).expand(n, s + 1) + 0.01 * torch.rand(n, s + 1)
    tdist = torch.sort(tdist, dim=-1).values
    fields = [model.evaluate(level, batch, tdist) for level in range(2)]
    total = sum((f["density"].sum() + f["rgb"].square().sum()) for f in fields)
    total.backward()
    return fields, {k: p.grad.clone() for k, p in model.named_parameters()}


def assert_grads_close(fused, plain, atol):
    for key, grad in plain.items():
        scale = float(grad.abs().max()) + 1e-12
        torch.testing.assert_close(fused[key] / scale, grad / scale, rtol=0, atol=atol, msg=key)


@pytest.mark.parametrize("name", NAMES)
def test_fused_fields_match_the_straightforward_ones_in_fp32(name, monkeypatch):
    model, batch = small_paper_layout(name), rays()
    torch.manual_seed(1)
    fused, fused_grads = fields_and_grads(model, batch)
    monkeypatch.setattr(SkipMLP, "forward", plain_forward)
    torch.manual_seed(1)
    plain, plain_grads = fields_and_grads(model, batch)
    for level_fused, level_plain in zip(fused, plain, strict=True):
        assert level_fused.keys() == level_plain.keys()
        for key, value in level_plain.items():
            torch.testing.assert_close(level_fused[key], value, rtol=1e-4, atol=1e-5, msg=key)
    assert_grads_close(fused_grads, plain_grads, atol=1e-4)


@pytest.mark.parametrize("name", NAMES)
def test_fused_training_step_matches_the_straightforward_one(name, monkeypatch):
    """The whole training loss (both levels, importance resampling, Ref-NeRF's regularisers) and every
    parameter's gradient, in float64 so that the resampling sees the same coarse weights."""
    model, batch = small_paper_layout(name).double(), rays(dtype=torch.float64)
    fused_out, fused_loss, fused_grads = loss_and_grads(model, batch)
    monkeypatch.setattr(SkipMLP, "forward", plain_forward)
    plain_out, plain_loss, plain_grads = loss_and_grads(model, batch)
    assert float(fused_loss) == pytest.approx(float(plain_loss), rel=1e-12)
    for level_fused, level_plain in zip(fused_out, plain_out, strict=True):
        for key in ("rgb", "depth", "acc", "weights", "tdist"):
            torch.testing.assert_close(level_fused[key], level_plain[key], rtol=1e-10, atol=1e-12)
    assert_grads_close(fused_grads, plain_grads, atol=1e-10)


def test_skip_mlp_pieces_and_per_ray_broadcast():
    """forward(a, b) == forward(cat(a, b)); a (N, 1, c) piece is broadcast over the samples; a skip after
    the last layer returns the concatenation; values and input gradients match the plain form."""
    torch.manual_seed(0)
    mlp = SkipMLP(7, depth=3, width=8, skip_layer=2)  # skip after layer 2, the last one
    a = torch.randn(4, 5, 5, requires_grad=True)
    b = torch.randn(4, 1, 2, requires_grad=True)
    fused = mlp(a, b)
    plain = plain_forward(mlp, a, b)
    assert fused.shape == (4, 5, 8 + 7) == plain.shape
    torch.testing.assert_close(fused, plain)
    g_fused = torch.autograd.grad(fused.square().sum(), (a, b))
    g_plain = torch.autograd.grad(plain.square().sum(), (a, b))
    for f, p in zip(g_fused, g_plain, strict=True):
        torch.testing.assert_close(f, p)
