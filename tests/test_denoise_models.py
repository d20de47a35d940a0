"""Learned denoisers: parameter counts at paper size, kernel application against a brute-force reference,
whitening buffers, shared branches, tiled inference, FLOP counting, building from config and the benchmark."""

from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from torch import nn

from src.bench.cli import main as bench_main
from src.data.features import PAPER_CHANNELS
from src.data.kpcn_preprocess import WhiteningStats
from src.errors import ConfigError, DataError
from src.models.denoise.base import Denoiser
from src.models.denoise.kernels import apply_kernel, default_order, kernel_application_flops
from src.models.denoise.models import BranchDenoiser, infer_tiled
from src.models.denoise.networks import ConvStack, ResidualKernelNet
from src.models.denoise.summary import flops_per_pixel, model_summary, random_batch
from src.models.instantiate import build_method
from src.models.parameters import count_parameters
from tests.conftest import CONF_DIR, ROOT, assert_loads_from_legacy_checkpoint, compose_config, one_line_error

C_IN = len(PAPER_CHANNELS)


def assert_close(
    actual: torch.Tensor, expected: torch.Tensor, rtol: float = 1e-5, atol: float = 1e-6
) -> None:
    """allclose with the worst difference in the message (torch.testing.assert_close would first import
    torch.distributed, ~4 s, on every test process)."""
    assert actual.shape == expected.shape, (actual.shape, expected.shape)
    expected = expected.to(actual.dtype)
    worst = (actual - expected).abs().max().item() if actual.numel() else 0.0
    assert torch.allclose(actual, expected, rtol=rtol, atol=atol), f"max abs difference {worst}"


def naive_apply_kernel(logits: torch.Tensor, image: torch.Tensor, k: int) -> torch.Tensor:
    """Reference, the memory-hungry way the implementation avoids: pad by clamping indices (= replicate
    padding), `F.unfold` every k x k window, torch.softmax the scores, weighted sum; in float64.
    Only for tiny images."""
    n, c, h, w = image.shape
    r = k // 2
    rows = torch.clamp(torch.arange(-r, h + r), 0, h - 1)
    cols = torch.clamp(torch.arange(-r, w + r), 0, w - 1)
    padded = image.double()[:, :, rows][:, :, :, cols]
    # unfold's channel index is c * k*k + i * k + j: the (i, j) tap of channel c, as `apply_kernel` expects.
    windows = F.unfold(padded, k).view(n, c, k * k, h, w)
    weights = torch.softmax(logits.double(), dim=1)
    return (windows * weights.unsqueeze(1)).sum(dim=2)


def paper_model(name: str, **overrides):
    cfg = compose_config(
        [f"model={name}", "profile=paper", *(f"model.{k}={v}" for k, v in overrides.items())]
    )
    return build_method(cfg.model), cfg.model


def tiny_cfg(**overrides):
    cfg = {
        "name": "tiny",
        "_target_": "src.models.denoise.models.conv_stack_denoiser",
        "output": "kernel",
        "kernel_size": 3,
        "shared": False,
        "whiten": True,
        "in_channels": C_IN,
        "width": 4,
        "depth": 2,
        "conv_kernel": 3,
    }
    return {**cfg, **overrides}


# --- parameter counts (paper configs) ---------------------------------------------------------------


@pytest.mark.parametrize(("name", "per_branch"), [("dpcn", 1_828_303), ("kpcn", 2_923_741)])
def test_paper_parameter_counts_per_branch(name, per_branch):
    model, _ = paper_model(name)
    assert not model.shared
    assert count_parameters(model.diffuse_net) == count_parameters(model.specular_net) == per_branch
    assert count_parameters(model) == 2 * per_branch


def test_residual_kpcn_shared_and_separate_counts():
    shared, _ = paper_model("resnet")
    assert shared.shared and shared.diffuse_net is shared.specular_net
    assert count_parameters(shared) == 972_217
    separate, _ = paper_model("resnet", shared="false")
    assert separate.diffuse_net is not separate.specular_net
    assert count_parameters(separate) == 2 * 972_217


def test_networks_alone_match_the_documented_sizes():
    assert count_parameters(ConvStack(28, 100, 9, 5, 3)) == 1_828_303
    assert count_parameters(ConvStack(28, 100, 9, 5, 441)) == 2_923_741
    assert count_parameters(ResidualKernelNet(28, 64, 12, 3, 64, 441)) == 972_217


# --- kernel application --------------------------------------------------------------------------


ORDERS = ("offset", "row")


@pytest.mark.parametrize("order", ORDERS)
@pytest.mark.parametrize("k", [1, 5, 21])
def test_apply_kernel_matches_naive_reference(k, order):
    # Non-square, N=2, and k=21 larger than the image: every tap of the corner pixels is a border tap.
    gen = torch.Generator().manual_seed(k)
    n, c, h, w = 2, 3, 7, 11
    logits = 4 * torch.randn(n, k * k, h, w, generator=gen)
    image = torch.randn(n, c, h, w, generator=gen)
    out = apply_kernel(logits, image, k, order=order)
    assert out.shape == (n, c, h, w) and out.dtype == torch.float32
    assert_close(out.double(), naive_apply_kernel(logits, image, k), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("order", ORDERS)
def test_apply_kernel_offset_convention(order):
    # All weight on tap (i, j) = (0, 2) of a 3x3 kernel: out[y, x] = image[y - 1, x + 1] (clamped).
    k, h, w = 3, 4, 5
    logits = torch.full((1, k * k, h, w), -1e4)
    logits[:, 0 * k + 2] = 0.0
    image = torch.arange(h * w, dtype=torch.float32).view(1, 1, h, w)
    out = apply_kernel(logits, image, k, order=order)[0, 0]
    rows = torch.clamp(torch.arange(h) - 1, 0, h - 1)
    cols = torch.clamp(torch.arange(w) + 1, 0, w - 1)
    assert_close(out, image[0, 0][rows][:, cols])


@pytest.mark.parametrize("order", ORDERS)
def test_apply_kernel_gradients_match_reference(order):
    gen = torch.Generator().manual_seed(1)
    k = 5
    logits = torch.randn(2, k * k, 4, 6, generator=gen, dtype=torch.float64, requires_grad=True)
    image = torch.randn(2, 3, 4, 6, generator=gen, dtype=torch.float64, requires_grad=True)
    weights = torch.randn(2, 3, 4, 6, generator=gen, dtype=torch.float64)
    (apply_kernel(logits, image, k, order=order) * weights).sum().backward()
    got = logits.grad.clone(), image.grad.clone()
    logits.grad, image.grad = None, None
    (naive_apply_kernel(logits, image, k) * weights).sum().backward()
    assert_close(got[0], logits.grad)
    assert_close(got[1], image.grad)


@pytest.mark.parametrize("order", ORDERS)
def test_softmax_kernel_preserves_a_constant_image_and_large_logits_are_stable(order):
    logits = 1e4 * torch.randn(2, 21 * 21, 9, 13)  # exp() of these would overflow without the max shift
    image = torch.full((2, 3, 9, 13), 0.7)
    out = apply_kernel(logits, image, 21, order=order)
    assert torch.isfinite(out).all()
    assert_close(out, image)


@pytest.mark.parametrize("order", ORDERS)
def test_apply_kernel_under_bf16_autocast_accumulates_in_float32(order):
    logits = torch.randn(1, 25, 6, 7).bfloat16()
    image = torch.rand(1, 3, 6, 7).bfloat16()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = apply_kernel(logits, image, 5, order=order)
    assert out.dtype == torch.float32
    expected = naive_apply_kernel(logits.float(), image.float(), 5)
    assert_close(out.double(), expected, rtol=1e-5, atol=1e-6)


def test_apply_kernel_default_order_is_row_under_autograd_and_offset_for_cpu_inference():
    logits = torch.randn(1, 9, 4, 5, requires_grad=True)
    image = torch.rand(1, 3, 4, 5)
    assert default_order(logits, image) == "row"
    with torch.no_grad():
        assert default_order(logits, image) == "offset"
    assert default_order(logits.detach(), image) == "offset"
    assert default_order(logits.detach(), image.requires_grad_()) == "row"


def test_apply_kernel_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="k\\*k|25"):
        apply_kernel(torch.zeros(1, 9, 4, 4), torch.zeros(1, 3, 4, 4), 5)


@pytest.mark.parametrize(
    ("logits_shape", "image_shape", "k", "match"),
    [
        ((1, 16, 4, 4), (1, 3, 4, 4), 4, "odd"),  # even, with matching logits: must still be refused
        ((1, 0, 4, 4), (1, 3, 4, 4), 0, "odd"),
        ((1, 9, 4, 4), (1, 4, 4), 3, "N, C, H, W"),  # 3-D image, 4-D logits
    ],
)
def test_apply_kernel_rejects_bad_kernel_sizes_and_ranks(logits_shape, image_shape, k, match):
    with pytest.raises(ValueError, match=match):
        apply_kernel(torch.zeros(logits_shape), torch.zeros(image_shape), k)


def test_apply_kernel_default_order_on_cpu_is_offset(monkeypatch):
    # Both orders give the same numbers (tested above); the CPU default is the cache-friendly one.
    from src.models.denoise import kernels

    used = []
    for name, fn in list(kernels.ACCUMULATORS.items()):
        monkeypatch.setitem(kernels.ACCUMULATORS, name, lambda *a, _n=name, _f=fn: used.append(_n) or _f(*a))
    apply_kernel(torch.zeros(1, 9, 4, 4), torch.zeros(1, 3, 4, 4), 3)
    assert used == ["offset"]


def test_apply_kernel_upcasts_a_half_precision_image():
    gen = torch.Generator().manual_seed(3)
    logits = torch.randn(1, 9, 5, 6, generator=gen)
    image = torch.rand(1, 3, 5, 6, generator=gen).half()  # float32 logits, float16 image
    out = apply_kernel(logits, image, 3)
    assert out.dtype == torch.float32
    assert_close(out.double(), naive_apply_kernel(logits, image.float(), 3), rtol=1e-6, atol=1e-6)


# Surviving mutants of src/models/denoise/kernels.py (bash scripts/mutation.sh kernels), all equivalent here:
# - `"row" if image.device.type == "cuda" else "offset"` with "row"/"cuda" misspelt or the test forced
#   False (5 mutants): only changes the choice on a CUDA device; the CPU default is pinned by
#   test_apply_kernel_default_order_on_cpu_is_offset, and both orders give the same numbers.
# - `F.pad(...) if r > 0 else image` -> `if r >= 0` / `if (r > 0) or True`: replicate padding by 0 pixels
#   (k = 1) is a no-op.
# - `image.shape[-2:]` -> `image.shape[+2:]`: the same two dimensions of a 4-D tensor.


# --- models --------------------------------------------------------------------------------------


def test_shared_branches_run_one_network_once_on_both():
    model = build_method(tiny_cfg(shared=True, whiten=False))
    calls = []
    model.diffuse_net.register_forward_hook(lambda m, i, o: calls.append(i[0].shape[0]))
    batch = random_batch(5, 6, batch_size=2, generator=torch.Generator().manual_seed(0))
    out = model(batch)
    assert model.diffuse_net is model.specular_net and calls == [4]  # one call on 2 + 2 images
    # Same as running the shared net on each branch separately.
    for branch in ("diffuse", "specular"):
        logits = model.diffuse_net(batch[f"{branch}_in"])
        assert_close(out[branch], apply_kernel(logits, batch[f"{branch}_t"], 3))


def test_direct_output_is_the_network_output():
    model = build_method(tiny_cfg(output="direct", whiten=False))
    batch = random_batch(4, 5, generator=torch.Generator().manual_seed(0))
    out = model(batch)
    assert set(out) == {"diffuse", "specular"} and out["diffuse"].shape == (1, 3, 4, 5)
    assert_close(out["specular"], model.specular_net(batch["specular_in"]))


def _stats(seed: int) -> WhiteningStats:
    rng = np.random.default_rng(seed)
    return WhiteningStats(rng.normal(size=C_IN), rng.uniform(0.5, 2.0, size=C_IN))


def test_whitening_buffers_are_applied_and_persist_through_state_dict():
    stats = {"diffuse_in": _stats(1), "specular_in": _stats(2)}
    torch.manual_seed(0)
    model = build_method(tiny_cfg(output="direct"), whitening=stats)
    assert {"diffuse_mean", "diffuse_std", "specular_mean", "specular_std"} <= set(model.state_dict())
    batch = random_batch(4, 5, generator=torch.Generator().manual_seed(0))
    whitened = (batch["diffuse_in"] - torch.tensor(stats["diffuse_in"].mean).float().view(1, -1, 1, 1)) / (
        torch.tensor(stats["diffuse_in"].std).float().view(1, -1, 1, 1)
    )
    assert_close(model(batch)["diffuse"], model.diffuse_net(whitened))
    # A fresh model without stats starts at identity whitening; loading the checkpoint restores them.
    fresh = build_method(tiny_cfg(output="direct"))
    assert torch.all(fresh.diffuse_mean == 0) and torch.all(fresh.diffuse_std == 1)
    fresh.load_state_dict(model.state_dict())
    assert_close(fresh(batch)["specular"], model(batch)["specular"])


def test_whitening_of_the_wrong_length_is_a_config_error():
    bad = {"diffuse_in": WhiteningStats(np.zeros(3), np.ones(3)), "specular_in": _stats(0)}
    with pytest.raises(ConfigError) as excinfo:
        build_method(tiny_cfg(), whitening=bad)
    one_line_error(excinfo, "diffuse_in", "28")


def test_halo_and_tiled_inference_equal_one_full_frame_pass():
    model = build_method(tiny_cfg(kernel_size=5)).eval()
    assert model.halo == 2 * 1 + 2  # 2 conv layers of 3x3 + the 5x5 kernel radius
    batch = random_batch(13, 17, batch_size=2, generator=torch.Generator().manual_seed(3))
    with torch.inference_mode():
        full = model(batch)
        tiled = infer_tiled(model, batch, tile=6)
    for branch in ("diffuse", "specular"):
        assert_close(tiled[branch], full[branch], atol=1e-5)


def test_residual_network_halo_and_shape():
    net = ResidualKernelNet(C_IN, 8, 2, 3, 8, 9)
    assert net.halo == (2 + 2 * 2) * 1
    assert net(torch.zeros(1, C_IN, 5, 7)).shape == (1, 9, 5, 7)


# --- building from config -----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("overrides", "needles"),
    [
        ({"_target_": None}, ["model._target_", "dotted path", "None"]),
        ({"_target_": "src.models.denoise.nope.Net"}, ["model._target_", "cannot import", "nope"]),
        ({"_target_": "src.models.denoise.models.BRANCHES"}, ["model._target_", "not a class or function"]),
        ({"widht": 4}, ["model.widht", "not an argument of conv_stack_denoiser", "'width'"]),
        ({"width": True}, ["model.width", "expected int", "True"]),
        ({"output": "x"}, ["model.output", "expected Literal['direct', 'kernel']", "'x'"]),
    ],
)
def test_bad_model_configs_are_one_line_errors_naming_the_key(overrides, needles):
    with pytest.raises(ConfigError) as excinfo:
        build_method(tiny_cfg(**overrides))
    one_line_error(excinfo, *needles)


def test_a_missing_argument_is_named():
    cfg = tiny_cfg()
    del cfg["depth"]
    with pytest.raises(ConfigError) as excinfo:
        build_method(cfg)
    one_line_error(excinfo, "model.depth", "missing", "conv_stack_denoiser")


#: Every denoiser config under conf/model/ (the radiance fields, `family: nerf`, are not denoisers).
DENOISER_CONFIGS = sorted(
    p.stem for p in (Path(CONF_DIR) / "model").glob("*.yaml") if "family: nerf" not in p.read_text()
)


def test_the_denoiser_configs_are_found_by_their_files():
    assert {"dpcn", "kpcn", "resnet", "unet_kpcn", "cross_bilateral", "oidn", "gp_filter"} <= set(
        DENOISER_CONFIGS
    )
    assert not {"nerf", "mipnerf", "refnerf"} & set(DENOISER_CONFIGS)


@pytest.mark.parametrize("name", DENOISER_CONFIGS)
@pytest.mark.parametrize("dataset", ["procedural", "volumetric"])
@pytest.mark.parametrize("profile", ["smoke", "cpu", "paper"])
def test_every_denoiser_config_instantiates_on_every_denoising_kind(name, dataset, profile):
    """Each model config builds on the stills and on the sequences at every profile, and the config's
    `learned` (what the runs log and the ledger reads) is the built method's (what the trainer reads)."""
    cfg = compose_config([f"model={name}", f"dataset={dataset}", f"profile={profile}"]).model
    model = build_method(cfg)
    assert model.learned == cfg.learned and callable(model)


@pytest.mark.parametrize(
    ("overrides", "key"),
    [
        ({"width": None}, "model.width"),
        ({"conv_kernel": 4}, "model.conv_kernel"),
        ({"output": "x"}, "model.output"),
    ]
    + [({"shared": "yes"}, "model.shared"), ({"kernel_size": 0}, "model.kernel_size")],
)
def test_invalid_keys_name_the_key(overrides, key):
    with pytest.raises(ConfigError) as excinfo:
        build_method(tiny_cfg(**overrides))
    one_line_error(excinfo, key)


def test_build_method_accepts_dictconfig():
    model, cfg = paper_model("resnet", blocks=1, width=8, predictor_width=8)
    assert isinstance(model, BranchDenoiser) and model.halo == (2 + 2) * 1 + 10
    assert count_parameters(model) > 0 and cfg._target_.endswith("residual_denoiser")


# --- FLOPs and summary ---------------------------------------------------------------------------


def test_flops_per_pixel_of_a_conv_stack_matches_the_closed_form():
    c_in, width, depth, k, c_out = C_IN, 6, 3, 5, 9
    sizes = [c_in] + [width] * (depth - 1) + [c_out]
    closed = 2 * sum(a * b * k * k for a, b in zip(sizes[:-1], sizes[1:], strict=True))
    net = ConvStack(c_in, width, depth, k, c_out)
    assert flops_per_pixel(net, in_channels=c_in) == {"total": closed, "conv": closed, "kernel": 0}
    # A two-branch kernel model: both branches' convs plus their kernel applications (k_kernel = 3).
    model = build_method(tiny_cfg(width=6, depth=3, conv_kernel=5, kernel_size=3))
    flops = flops_per_pixel(model)
    per_branch_conv = 2 * (c_in * 6 * 25 + 6 * 6 * 25 + 6 * 9 * 25)
    assert flops["conv"] == 2 * per_branch_conv
    assert flops["kernel"] == 2 * (2 * 9 * 3 + 3 * 9)
    assert flops["total"] == flops["conv"] + flops["kernel"]


class _OneBranchKernel(Denoiser):
    """A user's one-branch kernel predictor (k = 5) on the diffuse inputs, outputting colour."""

    kernel_size = 5

    def __init__(self) -> None:
        super().__init__()
        self.net = nn.Conv2d(C_IN, 25, 1)

    @property
    def halo(self) -> int:
        return 2

    def forward(self, batch):
        return {"color": apply_kernel(self.net(batch["diffuse_in"]), batch["color"], self.kernel_size)}


class _DeclaredOneBranchKernel(_OneBranchKernel):
    def kernel_flops_per_pixel(self) -> float:
        return kernel_application_flops(self.kernel_size)


def test_kernel_flops_are_what_a_denoiser_declares_not_read_from_its_attribute_names():
    """One kernel application of k = 5 is 2*25*3 + 3*25 = 225 FLOPs per pixel; the summary once counted
    every model with a `kernel_size` as two branches (450). A model that declares nothing adds none."""
    assert kernel_application_flops(5) == 225
    conv = 2 * C_IN * 25
    assert flops_per_pixel(_DeclaredOneBranchKernel()) == {"total": conv + 225, "conv": conv, "kernel": 225}
    assert flops_per_pixel(_OneBranchKernel())["kernel"] == 0
    two_branch = build_method(tiny_cfg(kernel_size=5))
    assert flops_per_pixel(two_branch)["kernel"] == 2 * 225 == two_branch.kernel_flops_per_pixel()


def test_model_summary_reports_parameters_and_flops():
    model = build_method(tiny_cfg())
    text = model_summary(model, tiny_cfg())
    assert f"parameters: {count_parameters(model):,}" in text
    assert "FLOPs per pixel" in text and "kernel application" in text and "1280x720" in text


# --- benchmark -----------------------------------------------------------------------------------


def test_bench_runs_on_a_tiny_frame_and_prints_the_ratios(capsys):
    code = bench_main(
        [
            "denoise",
            "--width",
            "24",
            "--height",
            "16",
            "--profile",
            "smoke",
            "--rounds",
            "5",
            "--warmup",
            "0",
        ]
    )
    out = capsys.readouterr().out
    assert code == 0, out
    for needle in ("dpcn", "kpcn (net only)", "resnet", "oidn", "conv2d 100->100 5x5", "KPCN / DPCN time"):
        assert needle in out, (needle, out)
    assert "FLOP ratio KPCN / DPCN" in out and "kernel-application overhead, kpcn" in out


def test_a_checkpoint_from_before_target_configs_still_loads(tmp_path):
    # Checkpoints written before `model._target_` named the builder carry `model.architecture` instead.
    from src.train.checkpoint import load_weights

    cfg = tiny_cfg(whiten=False)
    legacy = {k: v for k, v in cfg.items() if k != "_target_"} | {"architecture": "conv_stack"}
    assert_loads_from_legacy_checkpoint(cfg, legacy, tmp_path / "old.pt")
    # ...but not into a different network: the one-line error names what changed.
    with pytest.raises(DataError) as excinfo:
        load_weights(
            build_method(tiny_cfg(whiten=False, width=5)),
            tiny_cfg(whiten=False, width=5),
            tmp_path / "old.pt",
        )
    one_line_error(excinfo, "old.pt", "model.width: 4 in checkpoint vs 5")


def test_a_sequence_checkpoint_from_the_frame_builders_loads_into_the_one_branch_model(tmp_path):
    """Before one batch contract (issue 31) the sequences' KPCN was `frame_conv_stack_denoiser` (one `net`,
    a `transform` key); its checkpoints load into today's builder with `branches: [radiance]`."""
    from src.train.checkpoint import load_weights, save_checkpoint

    cfg = tiny_cfg(whiten=False, branches=["radiance"])
    torch.manual_seed(0)
    trained = build_method(cfg)
    frame_target = "src.models.denoise.frame_models.frame_conv_stack_denoiser"
    old_cfg = {k: v for k, v in cfg.items() if k != "branches"} | {"_target_": frame_target}
    old_cfg["transform"] = "log_modulus"
    weights = {k.replace("radiance_net.", "net.", 1): v for k, v in trained.state_dict().items()}
    state = {"model": weights, "model_config": old_cfg, "optimizer": {}, "epoch": 1, "batch_in_epoch": 0}
    save_checkpoint(tmp_path / "frame.pt", state | {"step": 5})
    torch.manual_seed(1)
    fresh = build_method(cfg)
    load_weights(fresh, cfg, tmp_path / "frame.pt")
    for key, value in trained.state_dict().items():
        assert torch.equal(fresh.state_dict()[key], value), key
    with pytest.raises(DataError) as excinfo:  # not into the still images' two branches
        load_weights(build_method(tiny_cfg(whiten=False)), tiny_cfg(whiten=False), tmp_path / "frame.pt")
    one_line_error(
        excinfo, "frame.pt", "model.branches: ['radiance'] in checkpoint vs ['diffuse', 'specular']"
    )


@pytest.mark.parametrize("profile", ["smoke", "cpu", "paper"])
def test_whitening_is_an_ablation_off_by_default(profile):
    """Seed thesis Sec. 6 (Figs. 6.9-6.10): input whitening of the separate-weights residual model was an
    ablation that made the specular loss worse. No learned model whitens unless asked; the `whitening`
    sweep runs both arms and the comparison sweeps leave it at the default."""
    for name in compose_config().compare.denoise.learned:
        assert compose_config([f"model={name}", f"profile={profile}"]).model.whiten is False, name
    sweeps = ROOT / "conf" / "sweep"
    assert "model.whiten: true,false" in (sweeps / "whitening.yaml").read_text()
    for sweep in ("denoisers", "shared_vs_separate"):
        assert "whiten" not in (sweeps / f"{sweep}.yaml").read_text(), sweep


def test_a_new_kernel_predictor_is_one_network_maker_given_to_branch_denoiser():
    """What docs/extending.md shows for a KPCN variant (a dilated backbone): a maker out_channels ->
    network handed to the public `branch_denoiser` gets the branches, the kernel output, whitening and
    sharing of DPCN/KPCN. With all kernel scores equal the output is the k x k box mean of each branch."""
    from src.models.denoise.models import branch_denoiser

    class Dilated(nn.Module):
        def __init__(self, in_channels: int, out_channels: int) -> None:
            super().__init__()
            self.conv = nn.Conv2d(in_channels, out_channels, 3, padding=2, dilation=2)
            nn.init.zeros_(self.conv.weight)
            nn.init.zeros_(self.conv.bias)

        def forward(self, x):
            return self.conv(x)

    in_channels = 5
    model = branch_denoiser(
        lambda out: Dilated(in_channels, out),
        in_channels,
        {"output": "kernel", "kernel_size": 3, "shared": False, "whiten": False},
    )
    assert model.branches == ("diffuse", "specular") and model.diffuse_net is not model.specular_net
    assert model.diffuse_net.conv.out_channels == 9
    batch = random_batch(8, 8, in_channels=in_channels, generator=torch.Generator().manual_seed(0))
    out = model(batch)
    for branch in ("diffuse", "specular"):
        box = F.avg_pool2d(F.pad(batch[f"{branch}_t"], (1, 1, 1, 1), mode="replicate"), 3, stride=1)
        # interior pixels: the padding the kernel application uses at the border may differ from this one
        assert torch.allclose(out[branch][..., 1:-1, 1:-1], box[..., 1:-1, 1:-1], atol=1e-5)
    shared = branch_denoiser(
        lambda out: Dilated(in_channels, out),
        in_channels,
        {"output": "direct", "shared": True, "whiten": False},
    )
    assert shared.diffuse_net is shared.specular_net and shared.diffuse_net.conv.out_channels == 3
