"""Radiance-field training options for fidelity to the papers and for one GPU (issue 15 items 9-10):
gradient accumulation over ray micro-batches (the same optimiser step as the unsplit batch), the
activation-memory estimate and its CUDA check, the thesis schedules, single-image batching and NeRF's
opaque last interval."""

import copy

import pytest
import torch
from omegaconf import OmegaConf

from src.models.instantiate import build_method
from src.train.nerf_trainer import optimizer_step
from tests.conftest import compose_config

NAMES = ("nerf", "mipnerf", "refnerf")


@pytest.fixture(autouse=True, scope="module")
def single_thread():
    """Tiny tensors: intra-op threads cost more than they gain on a 2-core machine."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def model_cfg(name: str, profile: str = "smoke", *overrides: str) -> dict:
    cfg = compose_config(["task=nerf", f"model={name}", f"profile={profile}", *overrides])
    return OmegaConf.to_container(cfg.model, resolve=True)


def random_rays(n: int, dtype=torch.float64, seed: int = 0) -> dict[str, torch.Tensor]:
    """Rays from cameras around the origin looking roughly at it, with random target colours."""
    gen = torch.Generator().manual_seed(seed)
    origins = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=dtype), dim=-1) * 3
    directions = -origins / 3 + 0.2 * torch.randn(n, 3, generator=gen, dtype=dtype)
    return {
        "origins": origins,
        "directions": directions,
        "viewdirs": torch.nn.functional.normalize(directions, dim=-1),
        "radii": torch.full((n, 1), 0.01, dtype=dtype),
        "near": torch.full((n, 1), 1.0, dtype=dtype),
        "far": torch.full((n, 1), 5.0, dtype=dtype),
        "rgb": torch.rand(n, 3, generator=gen, dtype=dtype),
    }


def one_step(model, batch, micro_batch_rays, grad_max_norm):
    """A copy of `model` after one Adam step on `batch` (jitter from the global RNG, seeded)."""
    model = copy.deepcopy(model)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-3)
    torch.manual_seed(7)
    values = optimizer_step(model, optimizer, batch, micro_batch_rays, grad_max_norm)
    return model, values


def max_abs_difference(a: torch.nn.Module, b: torch.nn.Module) -> float:
    pairs = zip(a.parameters(), b.parameters(), strict=True)
    return max(float((p - q).detach().abs().max()) for p, q in pairs)


# --- item 9a: gradient accumulation ----------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_micro_batches_reproduce_the_unsplit_step(name):
    """Split into micro-batches of 16, 8 and 5 rays (the last one shorter), one step lands on the same
    parameters as the unsplit step of 32 rays; Ref-NeRF with both regularisers on, grad clipping on."""
    torch.manual_seed(0)
    overrides = ["model.orientation_loss_mult=0.5", "model.pred_normal_loss_mult=0.1"]
    model = build_method(model_cfg(name, "smoke", *(overrides if name == "refnerf" else []))).double()
    batch = random_rays(32)
    whole, whole_values = one_step(model, batch, None, grad_max_norm=1e-2)
    for micro in (16, 8, 5):
        split, split_values = one_step(model, batch, micro, grad_max_norm=1e-2)
        diff = max_abs_difference(whole, split)
        assert diff < 1e-9, (micro, diff)
        assert split_values == pytest.approx(whole_values, rel=1e-9)
    assert max_abs_difference(whole, model) > 1e-4  # the step did something
