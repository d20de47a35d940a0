"""The bf16 training path of the radiance fields (`task.train.amp` on CUDA, `src.bench nerf --autocast
bf16`), checked against fp32 on the CPU: the MLPs' linear layers run in bf16 while compositing and the
losses stay in fp32, and a step's loss and gradients agree with the fp32 step's."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf
from torch import nn

from src.models.nerf import models
from src.models.nerf.fields import SkipMLP
from src.train import device
from src.train.device import autocast
from src.train.nerf_trainer import NerfTrainer, accumulate_gradients
from tests.test_nerf_fused import NAMES, rays, small_paper_layout

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py


def step(model, batch, noise, dtype):
    """Loss and every parameter's gradient of one unsplit step under autocast to `dtype` (None: fp32)."""
    model.zero_grad(set_to_none=True)
    values = accumulate_gradients(model, batch, None, noise, dtype)
    return values["loss"], {k: p.grad.clone() for k, p in model.named_parameters() if p.grad is not None}


def paper_weighted(name: str):
    """`small_paper_layout` with Ref-NeRF's regularisers back at the paper's weights (0.1, 3e-4)."""
    model = small_paper_layout(name)
    if name == "refnerf":
        model.orientation_loss_mult, model.pred_normal_loss_mult = 0.1, 3e-4
    return model


@pytest.mark.parametrize("name", NAMES)
def test_bf16_autocast_step_agrees_with_fp32(name):
    """Ref-NeRF's density gradient is taken in bf16 too: with its regularisers at 0.5 / 0.1 instead of
    the paper's weights, the trunk's gradients fall to cosine ~0.94 (measured), hence the paper's here."""
    model, batch = paper_weighted(name), rays(n=32)
    noise = model.draw_noise(32, batch["near"], torch.Generator().manual_seed(3))
    trunk = next(m for m in model.modules() if isinstance(m, SkipMLP))
    seen: list[torch.dtype] = []
    hook = trunk.register_forward_hook(lambda module, args, out: seen.append(out.dtype))
    loss32, grads32 = step(model, batch, noise, None)
    loss16, grads16 = step(model, batch, noise, torch.bfloat16)
    hook.remove()
    assert seen[0] == torch.float32 and seen[-1] == torch.bfloat16  # the bf16 step really ran in bf16
    assert loss16 == pytest.approx(loss32, rel=0.02)
    assert grads16.keys() == grads32.keys()
    flat16 = torch.cat([g.flatten() for g in grads16.values()])
    flat32 = torch.cat([g.flatten() for g in grads32.values()])
    assert F.cosine_similarity(flat16, flat32, dim=0) > 0.99
    assert float(flat16.norm()) == pytest.approx(float(flat32.norm()), rel=0.05)


@pytest.mark.parametrize("name", NAMES)
def test_compositing_stays_fp32_under_bf16_autocast(name, monkeypatch):
    """The fields reach compositing in fp32 (type promotion against the fp32 tdist alone would already
    make the outputs fp32, so the compositing functions' inputs are checked, not only the outputs), and
    the weights and colour equal a float64 composite of those (bf16-rounded) fields to fp32 precision;
    Ref-NeRF's per-sample outputs (read by its regularisers) are fp32 too."""
    seen: list[tuple[torch.Tensor, torch.Tensor]] = []
    weights_fn, render_fn = models.compute_alpha_weights, models.volumetric_rendering

    def spy_weights(density, tdist, dirs, opaque_last=False):
        seen.append((density, tdist))
        return weights_fn(density, tdist, dirs, opaque_last=opaque_last)

    def spy_render(rgb, weights, tdist, background):
        seen.append((rgb, weights))
        return render_fn(rgb, weights, tdist, background)

    monkeypatch.setattr(models, "compute_alpha_weights", spy_weights)
    monkeypatch.setattr(models, "volumetric_rendering", spy_render)
    model, batch = small_paper_layout(name), rays(n=8)
    with torch.no_grad(), autocast("cpu", torch.bfloat16):
        outputs = model(batch, randomized=False)
    assert len(seen) == 4  # (weights, render) per level
    for level, out in enumerate(outputs):
        (density, tdist), (rgb, _) = seen[2 * level], seen[2 * level + 1]
        assert density.dtype == rgb.dtype == torch.float32
        assert torch.equal(density, density.bfloat16().float())  # the MLP did run in bf16
        for key in ("rgb", "weights", "depth", "acc"):
            assert out[key].dtype == torch.float32, key
        # NeRF Eq. 3 in float64 from the fields as compositing received them.
        delta = tdist.double().diff(dim=-1) * batch["directions"].double().norm(dim=-1, keepdim=True)
        if model.opaque_background:
            delta[:, -1] = 1e10
        tau = density.double() * delta
        weights = (1 - torch.exp(-tau)) * torch.exp(-(torch.cumsum(tau, dim=-1) - tau))
        color = (weights[..., None] * rgb.double()).sum(dim=1) + (1 - weights.sum(dim=1, keepdim=True))
        torch.testing.assert_close(out["weights"].double(), weights, rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(out["rgb"].double(), color, rtol=1e-5, atol=1e-6)
        for key in ("sample_normals", "sample_normals_pred"):
            if key in out:
                assert out[key].dtype == torch.float32, key


def test_refnerf_density_normals_under_bf16_autocast_stay_close():
    """The density-gradient normals from a bf16 trunk: median angle to the fp32 ones under 2 degrees
    (measured 0.5; the weighted mean 3.1, where the gradient is small)."""
    model, batch = paper_weighted("refnerf"), rays(n=32)
    with torch.no_grad():
        fp32 = model(batch, randomized=False)[-1]["sample_normals"]
        with autocast("cpu", torch.bfloat16):
            bf16 = model(batch, randomized=False)[-1]["sample_normals"]
    angles = torch.rad2deg(torch.acos((fp32 * bf16).sum(dim=-1).clamp(-1.0, 1.0)))
    assert float(angles.median()) < 2.0


def test_float64_fields_are_not_narrowed():
    """The fp32 cast of the fields is for bf16/fp16 only: a float64 model composites in float64."""
    model, batch = small_paper_layout("mipnerf").double(), rays(n=4, dtype=torch.float64)
    outputs = model(batch, randomized=False)
    assert outputs[-1]["weights"].dtype == torch.float64 and outputs[-1]["rgb"].dtype == torch.float64


def amp_step(model, batch, amp: bool, monkeypatch):
    """`NerfTrainer.train_step` on the CPU with `task.train.amp` as on CUDA (`device.precision` patched to
    answer as for a CUDA device, so `autocast_dtype` picks bfloat16 through the trainer's own code path),
    spying every nn.Linear's (input, output) and what compositing and the loss receive."""
    monkeypatch.setattr(device, "precision", lambda amp, _: "bf16-autocast" if amp else "fp32")
    linear: list[tuple[nn.Module, tuple[torch.Tensor, ...], torch.Tensor]] = []
    hooks = [
        m.register_forward_hook(
            lambda m, args, out: linear.append((m, tuple(a.detach() for a in args), out.detach()))
        )
        for m in model.modules()
        if isinstance(m, nn.Linear | SkipMLP)
    ]
    fields: list[torch.Tensor] = []
    weights_fn = models.compute_alpha_weights
    monkeypatch.setattr(
        models,
        "compute_alpha_weights",
        lambda d, *a, **k: fields.append(d.detach()) or weights_fn(d, *a, **k),
    )
    rendered: list[torch.Tensor] = []
    loss_fn = model.loss
    monkeypatch.setattr(
        model, "loss", lambda out, rgb: rendered.append([o["rgb"].detach() for o in out]) or loss_fn(out, rgb)
    )
    trainer = SimpleNamespace(
        model=model,
        optimizer=torch.optim.SGD(model.parameters(), lr=0.0),
        cfg=OmegaConf.create({"seed": 0}),
        t=OmegaConf.create({"amp": amp, "grad_max_norm": None, "micro_batch_rays": None}),
        pos=SimpleNamespace(step=1),
        device=torch.device("cpu"),
    )
    values, size = NerfTrainer.train_step(trainer, batch)
    for hook in hooks:
        hook.remove()
    assert size == len(batch["rgb"])
    return values, linear, fields, rendered


def test_the_nerf_trainers_amp_step_runs_the_matmuls_in_bf16_and_the_loss_in_fp32(monkeypatch):
    """With amp, every linear layer's output is the bf16 product of its bf16-rounded input and
    parameters (by value), while the fields reach compositing in fp32 and the logged loss is the fp32
    mean squared error of the rendered colours (checked in float64: a bf16 loss is off by ~1e-3); with
    amp off the same step runs every layer in fp32."""
    model, batch = small_paper_layout("mipnerf"), rays(n=16)
    values, linear, fields, rendered = amp_step(model, batch, True, monkeypatch)
    trunks = [(m, args, out) for m, args, out in linear if isinstance(m, SkipMLP)]
    assert len(trunks) == 4 and len(linear) > 8 and len(fields) == 2 and len(rendered) == 1
    for layer, args, out in linear:
        assert out.dtype == torch.bfloat16, layer
        if isinstance(layer, nn.Linear):  # a head: exactly the bf16 product
            bias = None if layer.bias is None else layer.bias.bfloat16()
            expected = F.linear(args[0].bfloat16(), layer.weight.bfloat16(), bias)
            torch.testing.assert_close(out.float(), expected.float(), rtol=0, atol=0)
    for trunk, pieces, out in trunks:  # the fused trunk: the plain bf16 layers, up to bf16 rounding
        lead = torch.broadcast_shapes(*(p.shape[:-1] for p in pieces))
        x = torch.cat([p.expand(*lead, p.shape[-1]) for p in pieces], dim=-1).bfloat16()
        h = x
        for i, layer in enumerate(trunk.layers):
            h = F.relu(F.linear(h, layer.weight.bfloat16(), layer.bias.bfloat16()))
            h = torch.cat([h, x], dim=-1) if trunk._skip_after(i) else h
        torch.testing.assert_close(out.float(), h.float(), rtol=0.05, atol=0.05)
    assert all(d.dtype == torch.float32 for d in fields)
    (coarse, fine), target = (rgb.double() for rgb in rendered[0]), batch["rgb"].double()
    assert coarse.dtype == torch.float64 and rendered[0][0].dtype == torch.float32
    mse = ((coarse - target) ** 2).mean(), ((fine - target) ** 2).mean()
    assert values["loss"] == pytest.approx(float(0.1 * mse[0] + mse[1]), rel=1e-6)  # mip-NeRF's 0.1
    assert values["coarse"] == pytest.approx(float(mse[0]), rel=1e-6)
    values32, linear32, _, _ = amp_step(model, batch, False, monkeypatch)  # lr 0: the same parameters
    assert {out.dtype for _, _, out in linear32} == {torch.float32}
    assert values32["loss"] != values["loss"] and values32["loss"] == pytest.approx(values["loss"], rel=0.05)
