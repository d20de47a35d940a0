"""Radiance-field training options for fidelity to the papers and for one GPU (issue 15 items 9-10):
gradient accumulation over ray micro-batches (the same optimiser step as the unsplit batch), the
activation-memory estimate and its CUDA check, the thesis schedules, single-image batching and NeRF's
opaque last interval."""

import copy
import math

import pytest
import torch
from omegaconf import OmegaConf

from src.data.ray_batches import RayBatcher
from src.errors import ConfigError
from src.models.instantiate import build_method
from src.models.nerf.summary import activation_bytes_per_ray
from src.models.nerf.volume import compute_alpha_weights
from src.stages import print_model_summary
from src.train import nerf_trainer
from src.train.nerf_trainer import NerfTrainer, check_activation_memory, optimizer_step
from tests.conftest import compose_config, one_line_error, smoke_config

NAMES = ("nerf", "mipnerf", "refnerf")


pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py


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


# --- item 9b: activation memory --------------------------------------------------------------------------


def saved_bytes_per_ray(model, rays: int = 4) -> float:
    """Bytes of the tensors autograd saves for the backward of a training forward + loss, per ray (the
    difference of two ray counts, so nothing per batch counts)."""

    def measure(n):
        storages = {}

        def pack(tensor):
            storage = tensor.untyped_storage()
            storages[storage.data_ptr()] = storage.nbytes()
            return tensor

        batch = random_rays(n, torch.float32)
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda tensor: tensor):
            model.loss(model(batch, randomized=True), batch["rgb"])
        return sum(storages.values())

    return (measure(2 * rays) - measure(rays)) / rays


@pytest.mark.parametrize("name", NAMES)
@pytest.mark.parametrize(("profile", "tolerance"), [("smoke", 0.5), ("cpu", 0.1)])
def test_activation_estimate_matches_the_saved_tensors(name, profile, tolerance):
    model = build_method(model_cfg(name, profile))
    estimate = activation_bytes_per_ray(model)
    assert estimate == pytest.approx(saved_bytes_per_ray(model), rel=tolerance)


@pytest.mark.slow
@pytest.mark.parametrize("name", NAMES)
def test_activation_estimate_at_paper_size(name):
    model = build_method(model_cfg(name, "paper"))
    assert activation_bytes_per_ray(model) == pytest.approx(saved_bytes_per_ray(model, 2), rel=0.05)


def test_summary_prints_the_step_activation_memory(capsys):
    base = ["task=nerf", "model=refnerf", "profile=paper", "stage=summary"]
    print_model_summary(compose_config(base))
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert line.startswith("activation memory per training step (estimate, the whole batch): 119.")
    assert "16384 rays x 256 samples x 28.5 KB per sample" in line
    print_model_summary(compose_config([*base, "task.train.micro_batch_rays=4096"]))
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert "micro-batches of 4096 of 16384 rays): 29.83 GB" in line


def test_a_step_that_does_not_fit_the_gpu_is_one_line_naming_micro_batch_rays():
    model = build_method(model_cfg("refnerf", "paper"))
    per_ray = activation_bytes_per_ray(model)
    check_activation_memory(model, 16384, None, None)  # not CUDA: nothing to check
    check_activation_memory(model, 16384, None, 16384 * per_ray)  # fits exactly
    free = 80e9  # an 80 GB H100, empty
    with pytest.raises(ConfigError) as excinfo:
        check_activation_memory(model, 16384, None, free)
    one_line_error(excinfo, "task.train.micro_batch_rays=None", "119.3 GB", "80.0 GB free")
    one_line_error(excinfo, "set task.train.micro_batch_rays=8192 (or less)")
    assert 8192 * per_ray <= 0.8 * free < 16384 * per_ray
    check_activation_memory(model, 16384, 8192, free)  # the suggestion passes
    with pytest.raises(ConfigError) as excinfo:  # 8192 rays need about 60 GB
        check_activation_memory(model, 16384, 8192, 50e9)
    one_line_error(excinfo, "task.train.micro_batch_rays=8192", "set task.train.micro_batch_rays=4096")
    with pytest.raises(ConfigError) as excinfo:
        check_activation_memory(model, 16384, 1, per_ray / 2)
    one_line_error(excinfo, "not even one ray fits")


def test_the_trainer_checks_before_training(tmp_path, monkeypatch):
    """The trainer asks the device for its free memory (here injected: 100 kB, as if CUDA were full) and
    stops before loading any data; the CLI turns the ConfigError into exit status 2."""
    monkeypatch.setattr(nerf_trainer, "device_free_bytes", lambda device: 100_000)
    cfg = smoke_config(tmp_path, tmp_path / "run", ["task=nerf", "model=mipnerf"])
    with pytest.raises(ConfigError) as excinfo:
        NerfTrainer(cfg, tracker=None)
    one_line_error(excinfo, "task.train.micro_batch_rays=None", "set task.train.micro_batch_rays=")


# --- item 10a: single-image batching ---------------------------------------------------------------------


def batcher(batching: str, seed: int = 0, **kwargs) -> RayBatcher:
    images = torch.rand(6, 8, 10, 3, generator=torch.Generator().manual_seed(0))
    c2w = torch.eye(4)[:3].expand(6, 3, 4).clone()
    common = {"near": 2.0, "far": 6.0, "batch_size": 64, "seed": seed, "batching": batching}
    return RayBatcher(images, c2w, 10.0, **common, **kwargs)


def test_single_image_batches_draw_every_ray_from_one_image():
    single = batcher("single_image", precrop_iters=3)
    visited = set()
    for step in range(20):
        batch = single.batch(step)
        cams = batch["cam"].unique()
        assert len(cams) == 1, step
        visited.add(int(cams))
        assert torch.equal(batch["rgb"], single.images[batch["cam"], batch["row"], batch["col"]])
        again = batcher("single_image", precrop_iters=3).batch(step)  # the same (seed, step): the same
        assert all(torch.equal(again[k], batch[k]) for k in batch)
    assert len(visited) >= 4  # steps visit different images (6 images, 20 steps)
    assert len(batcher("all_images").batch(0)["cam"].unique()) > 1
    other_seed = [int(batcher("single_image", seed=1).batch(s)["cam"][0]) for s in range(20)]
    assert other_seed != [int(single.batch(s)["cam"][0]) for s in range(20)]
    with pytest.raises(ConfigError, match="batching='one_image'"):
        batcher("one_image")


# --- item 10b: NeRF's opaque last interval ---------------------------------------------------------------


def test_opaque_last_interval_closed_form():
    """Constant density sigma on [2, 6] cut into 4 intervals: with the real last interval the weights sum
    to 1 - exp(-4 sigma) (the background shows through); with NeRF's 1e10 one they sum to 1 and only the
    last weight changes, to exp(-3 sigma) (what passed the first three intervals)."""
    sigma = 0.3
    tdist = torch.linspace(2.0, 6.0, 5, dtype=torch.float64)[None]
    density = torch.full((1, 4), sigma, dtype=torch.float64)
    dirs = torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64)
    real, _, _ = compute_alpha_weights(density, tdist, dirs)
    opaque, _, _ = compute_alpha_weights(density, tdist, dirs, opaque_last=True)
    assert float(real.sum()) == pytest.approx(1 - math.exp(-4 * sigma), rel=1e-12)
    assert float(opaque.sum()) == pytest.approx(1.0, rel=1e-12)
    assert torch.equal(opaque[:, :3], real[:, :3])
    assert float(opaque[0, 3]) == pytest.approx(math.exp(-3 * sigma), rel=1e-12)
    # No density at all: nothing to make opaque, the background shows either way.
    empty, _, _ = compute_alpha_weights(torch.zeros_like(density), tdist, dirs, opaque_last=True)
    assert float(empty.sum()) == 0.0


def test_opaque_background_is_nerfs_default_only():
    """The model option reaches the renderer: NeRF's acc is 1 on every ray of constant positive density
    (softplus), mip-NeRF's (real intervals) is not."""
    rays = random_rays(8, torch.float32)
    for name, opaque in (("nerf", True), ("mipnerf", False), ("refnerf", False)):
        cfg = model_cfg(name)
        assert cfg["opaque_background"] is opaque
        model = build_method({**cfg, "density_activation": "softplus", "density_bias": 1.0})
        with torch.no_grad():
            for mlp in model.mlps:  # a constant field: density softplus(1) everywhere
                for p in mlp.parameters():
                    p.zero_()
        acc = model(rays, randomized=False)[-1]["acc"]
        if opaque:
            assert torch.allclose(acc, torch.ones_like(acc))
        else:
            assert bool((acc < 1 - 1e-3).all())
    with pytest.raises(ConfigError, match="model.opaque_background: expected bool, got 'yes'"):
        build_method({**model_cfg("nerf"), "opaque_background": "yes"})


# --- item 9c / 10c: the thesis schedules and NeRF's decay -----------------------------------------------


@pytest.mark.parametrize(
    ("model", "paper_steps", "lr", "lr_final", "clip", "like"),
    [
        ("nerf", 500_000, 5e-4, 5e-6, None, "nerf"),
        ("mipnerf", 1_000_000, 5e-4, 5e-6, None, "mipnerf"),
        ("refnerf", 250_000, 5e-4, 5e-6, None, "mipnerf"),
    ],
)
def test_the_thesis_profile_trains_each_model_as_the_thesis_says_for_1m_steps(
    model, paper_steps, lr, lr_final, clip, like
):
    """Grujčić 2023, Table 6.6: 1,000,000 iterations for every model; NeRF and mip-NeRF on their papers'
    settings, Ref-NeRF "the same way as mip-NeRF" (Sec. 4.3.2), not on multinerf's Ref-NeRF schedule."""
    paper = compose_config(["task=nerf", f"model={model}", "profile=paper"])
    thesis = compose_config(["task=nerf", f"model={model}", "profile=thesis"])
    assert paper.task.train.max_steps == paper_steps
    t = thesis.task.train
    assert (t.max_steps, t.lr_init, t.schedule.lr_final, t.grad_max_norm) == (1_000_000, lr, lr_final, clip)
    trained_like = compose_config(["task=nerf", f"model={like}", "profile=paper"]).task.train
    assert t.batch_size == trained_like.batch_size and t.optimizer == trained_like.optimizer
    assert t.schedule == compose_config(["task=nerf", f"model={like}", "profile=thesis"]).task.train.schedule
    assert (thesis.dataset.width, thesis.dataset.height) == (800, 800)
    assert thesis.profile_name == "thesis"


def test_nerf_schedules_decay_by_a_tenth_per_500k_steps():
    """NeRF's code: lr = lr_init 0.1^(step / 500k) (lrate_decay = 500); both profiles end on that curve."""
    for profile in ("paper", "thesis"):
        t = compose_config(["task=nerf", "model=nerf", f"profile={profile}"]).task.train
        assert t.schedule.delay_steps == 0
        expected = t.lr_init * 0.1 ** (t.max_steps / 500_000)
        assert t.schedule.lr_final == pytest.approx(expected, rel=1e-12), profile


@pytest.mark.parametrize("section", ["train", "eval"])
def test_render_chunk_is_cpu_chunk_on_a_cpu_and_chunk_elsewhere(section):
    """Validation and evaluation render `cpu_chunk` rays at a time on a CPU (paper: 64, whose activations
    stay in cache), `chunk` on a GPU, and `chunk` wherever `cpu_chunk` is null (the cpu profile)."""
    cpu, cuda = torch.device("cpu"), torch.device("cuda")
    paper = compose_config(["task=nerf", "profile=paper"]).task[section]
    assert (nerf_trainer.render_chunk(paper, cpu), nerf_trainer.render_chunk(paper, cuda)) == (64, 8192)
    small = compose_config(["task=nerf", "profile=cpu"]).task[section]
    assert small.cpu_chunk is None and nerf_trainer.render_chunk(small, cpu) == small.chunk == 1024
