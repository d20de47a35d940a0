"""The U-Net KPCN (`src/models/denoise/unet_kpcn.py`) and the KPCN family on the sequences' one `radiance`
branch (`src/models/denoise/models.py` with `branches: [radiance]`): the multi-scale kernels, Vogels et
al.'s scale composition, tiled inference, configs and `stage=summary`. Tiny sizes, CPU, a few seconds."""

import pytest
import torch
import torch.nn.functional as F
from omegaconf import OmegaConf

from src.data.color_spaces import RadianceTransform
from src.data.transforms import volume_transform
from src.errors import ConfigError
from src.models.denoise.base import final_color
from src.models.denoise.kernels import SOFTMAX_FLOPS_PER_TAP
from src.models.denoise.models import conv_stack_denoiser, infer_tiled
from src.models.denoise.summary import flops_per_pixel, model_summary, random_batch
from src.models.denoise.unet_kpcn import (
    COMPOSE_FLOPS,
    PYRAMID_FLOPS,
    ScaleCompositor,
    UNetKPCN,
    compose_scales,
    downsample,
    pad_to_multiple,
    radiance_pyramid,
    upsample,
)
from src.models.instantiate import build_method
from tests.conftest import compose_config, one_line_error, smoke_config

IN = 5


def tiny(**overrides):
    args = dict(
        in_channels=IN,
        widths=[4, 6, 8],
        convs_per_level=1,
        conv_kernel=3,
        kernel_size=3,
        compositor_width=4,
        components="color",
        filter_space="linear",
        transform="log_modulus",
    )
    torch.manual_seed(0)
    return UNetKPCN(**(args | overrides)).eval()


def random_frame_batch(height, width, in_channels=IN, seed=0):
    """A random batch of the sequences' radiance branch (`random_batch`)."""
    generator = torch.Generator().manual_seed(seed)
    return random_batch(height, width, in_channels=in_channels, branches=("radiance",), generator=generator)


def frame_batch(height, width, seed=0):
    return random_frame_batch(height, width, seed=seed)


def brute_force_kernel(logits, image, k):
    """out[y, x] = sum_ij softmax(logits)[ij, y, x] * image[clamp(y+i-r), clamp(x+j-r)], pixel by pixel."""
    n, c, h, w = image.shape
    r = k // 2
    weights = torch.softmax(logits.double(), dim=1)
    out = torch.zeros(n, c, h, w, dtype=torch.float64)
    for y in range(h):
        for x in range(w):
            for i in range(k):
                for j in range(k):
                    yy, xx = min(max(y + i - r, 0), h - 1), min(max(x + j - r, 0), w - 1)
                    out[:, :, y, x] += weights[:, i * k + j, y, x, None] * image[:, :, yy, xx].double()
    return out


def test_the_kernel_at_every_scale_is_a_softmax_window_over_that_scales_radiance():
    model = tiny()
    batch = frame_batch(12, 8)  # non-square; scales 12x8, 6x4, 3x2
    logits = model.kernel_logits(batch["radiance_in"])
    radiance = torch.rand(1, 3, 12, 8, generator=torch.Generator().manual_seed(1))
    filtered = model.filter_scales(logits, radiance)
    pyramid = radiance_pyramid(radiance, 3)
    assert [f.shape[-2:] for f in filtered] == [(12, 8), (6, 4), (3, 2)]
    for s in range(3):
        expected = brute_force_kernel(logits[s], pyramid[s], 3)
        torch.testing.assert_close(filtered[s].double(), expected, atol=1e-6, rtol=1e-6)


def test_downsample_of_upsample_is_the_identity_and_downsample_is_the_2x2_mean():
    c = torch.rand(2, 3, 3, 5)
    assert torch.equal(downsample(upsample(c)), c)
    x = torch.arange(16.0).view(1, 1, 4, 4)
    assert downsample(x)[0, 0, 0, 0] == (0 + 1 + 4 + 5) / 4


def test_the_composition_keeps_the_fine_scale_at_a_0_and_swaps_in_the_coarse_band_at_a_1():
    g = torch.Generator().manual_seed(2)
    fine, coarse = torch.rand(1, 3, 6, 4, generator=g), torch.rand(1, 3, 3, 2, generator=g)
    torch.testing.assert_close(compose_scales(fine, coarse, torch.zeros(1, 1, 6, 4)), fine)
    swapped = compose_scales(fine, coarse, torch.ones(1, 1, 6, 4))
    torch.testing.assert_close(swapped, fine - upsample(downsample(fine)) + upsample(coarse))
    torch.testing.assert_close(downsample(swapped), coarse)  # the coarse band is exactly c


def test_tiled_inference_equals_the_full_frame_on_a_non_square_frame():
    model = tiny()
    batch = frame_batch(61, 90)  # neither side a multiple of 2^(S-1) = 4
    assert model.halo % model.size_multiple == 0
    with torch.inference_mode():
        full = model(batch)["color"]
        tiled = infer_tiled(model, batch, tile=16)["color"]
    torch.testing.assert_close(tiled, full, atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize(("height", "width"), [(13, 7), (5, 17), (1, 1)])
def test_any_frame_size_comes_back_at_its_size(height, width):
    out = tiny()(frame_batch(height, width))["color"]
    assert out.shape == (1, 3, height, width)
    assert pad_to_multiple(torch.rand(1, 1, height, width), 4).shape[-2:] == (
        -(-height // 4) * 4,
        -(-width // 4) * 4,
    )


@pytest.mark.parametrize("components", ["color", "surface_volume"])
@pytest.mark.parametrize("filter_space", ["linear", "transformed"])
@pytest.mark.parametrize("transform", ["log_modulus", "none"])
def test_a_constant_radiance_stays_constant(components, filter_space, transform):
    model = tiny(components=components, filter_space=filter_space, transform=transform)
    batch = frame_batch(10, 14)
    value = {"radiance_t": 2.5, "surface_t": 1.5, "volume_t": 1.0}
    for key, v in value.items():
        batch[key] = volume_transform(torch.full((1, 3, 10, 14), v), transform)
    with torch.inference_mode():
        out = model(batch)["color"]
    torch.testing.assert_close(out, torch.full_like(out, 2.5), atol=1e-5, rtol=1e-5)


def test_surface_volume_has_two_kernel_heads_per_scale_and_twice_the_kernel_cost():
    one, two = tiny(), tiny(components="surface_volume")
    assert [h.out_channels for h in two.heads] == [2 * h.out_channels for h in one.heads]
    assert two.kernel_flops_per_pixel() == 2 * one.kernel_flops_per_pixel()


@pytest.mark.parametrize(
    ("model", "target"),
    [("kpcn", "conv_stack_denoiser"), ("dpcn", "conv_stack_denoiser"), ("resnet", "residual_denoiser")],
)
def test_the_kpcn_dpcn_and_resnet_configs_build_one_radiance_branch_on_the_sequences(model, target):
    """The same YAML and class as on still images; the data give one branch and its 62 input channels."""
    cfg = compose_config(["dataset=volumetric", f"model={model}", "profile=smoke"])
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    assert model_cfg["_target_"].endswith(f"models.{target}") and model_cfg["in_channels"] == 62
    assert model_cfg["branches"] == ["radiance"]
    net = build_method(model_cfg).eval()
    assert net.branches == ("radiance",) and not net.shared
    batch = random_frame_batch(9, 13, in_channels=62)
    with torch.inference_mode():
        out = net(batch)
        color = final_color(out, batch, RadianceTransform("log_modulus"))
    assert list(out) == ["radiance"] and color.shape == (1, 3, 9, 13) and torch.isfinite(color).all()
    with torch.inference_mode():  # tiled equals full frame here too (halo = receptive field)
        torch.testing.assert_close(
            infer_tiled(net, batch, tile=4)["radiance"], out["radiance"], atol=1e-5, rtol=1e-5
        )


def test_stage_summary_names_flops_per_pixel_and_the_volume_features():
    from src.tasks.denoise import DenoiseTask

    cfg = compose_config(["dataset=volumetric", "model=unet_kpcn", "dataset.volume_features=[color,albedo]"])
    model_cfg = OmegaConf.to_container(cfg.model, resolve=True)
    model = build_method(model_cfg)
    text = model_summary(model, model_cfg)
    assert "FLOPs per pixel" in text and "kernel application and composition" in text
    assert "in_channels 6" in text
    assert DenoiseTask.for_run(cfg).training_summary(model, cfg).endswith("6 channels): color, albedo")
    flops = flops_per_pixel(model)
    assert 0 < flops["compositor"] < flops["conv"] and flops["kernel"] == model.kernel_flops_per_pixel()


def test_the_paper_unet_kpcn_fits_the_cpu_budget():
    model_cfg = OmegaConf.to_container(
        compose_config(["dataset=volumetric", "model=unet_kpcn", "profile=paper"]).model, resolve=True
    )
    model = build_method(model_cfg)
    assert model.in_channels == 62 and 3 <= model.scales <= 5
    assert flops_per_pixel(model)["total"] <= 150_000


@pytest.mark.parametrize(
    ("key", "value", "needles"),
    [
        ("widht", 3, ["model.widht: not an argument of UNetKPCN"]),
        ("widths", [], ["model.widths", "non-empty list"]),
        ("widths", [8, 0], ["model.widths"]),
        ("kernel_size", 4, ["model.kernel_size", "odd"]),
        ("components", "diffuse", ["model.components", "surface_volume"]),
        ("filter_space", "log", ["model.filter_space", "transformed"]),
        ("transform", "log", ["model.transform", "log_modulus"]),
    ],
)
def test_a_bad_unet_kpcn_value_is_a_one_line_config_error(key, value, needles):
    model_cfg = OmegaConf.to_container(
        compose_config(["model=unet_kpcn", "profile=smoke"]).model, resolve=True
    )
    with pytest.raises(ConfigError) as excinfo:
        build_method(model_cfg | {key: value})
    one_line_error(excinfo, *needles)


def test_whitening_on_sequences_and_training_unet_kpcn_on_still_images_are_one_line_errors(tmp_path):
    from src.tasks.denoise import DenoiseTask

    cfg = compose_config(["dataset=volumetric", "model=kpcn", "profile=smoke", "model.whiten=true"])
    with pytest.raises(ConfigError) as excinfo:
        DenoiseTask.for_run(cfg).check_stages(["train"], cfg)
    one_line_error(excinfo, "model.whiten", "dataset=volumetric")
    # whitening matters to train and eval only
    DenoiseTask.for_run(cfg).check_stages(["render", "preprocess"], cfg)
    cfg = compose_config(["model=unet_kpcn", "profile=smoke"])
    for stage in ("train", "eval"):
        with pytest.raises(ConfigError) as excinfo:
            DenoiseTask.for_run(cfg).check_stages([stage], cfg)
        one_line_error(excinfo, "model=unet_kpcn", "radiance branch", f"stage={stage}", "dataset=procedural")
    volumetric = smoke_config(tmp_path, tmp_path / "run", ["dataset=volumetric", "model=unet_kpcn"])
    DenoiseTask.for_run(volumetric).check_stages(["train"], volumetric)


# --- the whole forward pass against an independent reference -------------------------------------------


def _lm(x):
    """sign(x) log(1 + |x|), written out."""
    return torch.sign(x) * torch.log1p(x.abs())


def _inverse_lm(y):
    return torch.sign(y) * torch.expm1(y.abs())


def _down(x):
    """2x2 block mean by reshaping."""
    n, c, h, w = x.shape
    return x.reshape(n, c, h // 2, 2, w // 2, 2).mean(dim=(3, 5))


def _up(x):
    """Each pixel repeated 2x2."""
    return x.repeat_interleave(2, dim=2).repeat_interleave(2, dim=3)


def _pad_replicate(x, multiple):
    """Bottom/right replicate padding by clamped indices."""
    h, w = x.shape[-2:]
    rows = torch.arange(-(-h // multiple) * multiple).clamp(max=h - 1)
    cols = torch.arange(-(-w // multiple) * multiple).clamp(max=w - 1)
    return x[..., rows, :][..., cols]


def _softmax_filter(scores, image, k):
    """sum_ij softmax(scores)[i*k+j] * image[y+i-r, x+j-r] with clamped (replicate) borders."""
    h, w = image.shape[-2:]
    r = k // 2
    weights = torch.softmax(scores, dim=1)
    rows = lambda i: (torch.arange(h) + i - r).clamp(0, h - 1)  # noqa: E731
    cols = lambda j: (torch.arange(w) + j - r).clamp(0, w - 1)  # noqa: E731
    return sum(
        weights[:, i * k + j, None] * image[..., rows(i), :][..., cols(j)] for i in range(k) for j in range(k)
    )


def _compositor(module, coarse_up, fine):
    """a = sigmoid(conv1x1(relu(conv_kxk([U(c), f])))) from the module's two convolutions' weights."""
    first, last = module.net[0], module.net[-1]
    hidden = F.conv2d(torch.cat([coarse_up, fine], dim=1), first.weight, first.bias, padding="same")
    return torch.sigmoid(F.conv2d(hidden.clamp(min=0), last.weight, last.bias))


def reference_forward(model, batch, *, kernel_of=None, compositor_of=None, pyramid_of_filtered=False):
    """The U-Net KPCN's output from its sub-networks (encoder/decoder blocks, heads, compositor nets) and
    the module docstring's definitions, in plain torch. The keyword arguments build plausible wrong
    variants: `kernel_of[c]` the kernel head serving component c, `compositor_of[c][s]` the (component,
    scale) compositor serving scale s of component c, `pyramid_of_filtered` r_{s+1} = D(f_s)."""
    keys = {"color": ("radiance_t",), "surface_volume": ("surface_t", "volume_t")}[model.components]
    scales, k = len(model.widths), model.kernel_size
    multiple = 2 ** (scales - 1)
    height, width = batch["radiance_in"].shape[-2:]
    skips, h = [], _pad_replicate(batch["radiance_in"], multiple)
    for s in range(scales):
        h = model.encoder[s](h if s == 0 else _down(h))
        skips.append(h)
    features = [None] * (scales - 1) + [h]
    for s in range(scales - 2, -1, -1):
        h = model.decoder[s](torch.cat([_up(h), skips[s]], dim=1))
        features[s] = h
    scores = [model.heads[s](features[s]) for s in range(scales)]
    log = model.transform == "log_modulus"
    linear = model.filter_space == "linear"
    out = 0
    for c, key in enumerate(keys):
        kc = c if kernel_of is None else kernel_of[c]
        r = _pad_replicate(batch[key], multiple)
        r = _inverse_lm(r) if linear and log else r
        filtered = []
        for s in range(scales):
            f = _softmax_filter(scores[s][:, kc * k * k : (kc + 1) * k * k], r, k)
            filtered.append(f)
            if s < scales - 1:
                r = _down(f if pyramid_of_filtered else r)
        to_net = _lm if linear and log else (lambda t: t)
        composed = filtered[-1]
        for s in range(scales - 2, -1, -1):
            cc, cs = (c, s) if compositor_of is None else compositor_of[c][s]
            a = _compositor(model.compositors[cc][cs], to_net(_up(composed)), to_net(filtered[s]))
            composed = filtered[s] - a * _up(_down(filtered[s])) + a * _up(composed)
        out = out + (_inverse_lm(composed) if not linear and log else composed)
    return out[..., :height, :width]


def varied_frame_batch(height, width, seed=0):
    """Two frames of unequal, non-constant radiance per component (ramps of different directions plus
    noise, some negative transformed values in the volume) and random inputs."""
    g = torch.Generator().manual_seed(seed)
    rows = torch.linspace(0, 1, height)[:, None].expand(height, width)
    cols = torch.linspace(0, 1, width)[None, :].expand(height, width)
    noise = lambda: torch.rand(2, 3, height, width, generator=g, dtype=torch.float64)  # noqa: E731
    surface = 2.5 * rows + 0.5 * cols + 0.8 * noise()
    volume = 1.5 * cols * (1 - rows) + 0.6 * noise() - 0.2
    inputs = 2 * torch.rand(2, IN, height, width, generator=g, dtype=torch.float64) - 1
    return {
        "radiance_in": inputs,
        "surface_t": surface,
        "volume_t": volume,
        "radiance_t": surface + 0.3 * volume,
    }


def sharpened(model):
    """The model in float64 with its kernel heads and compositor outputs scaled up, so that kernels are
    far from uniform and the blend weights a spread over (0, 1)."""
    model = model.double()
    with torch.no_grad():
        for head in model.heads:
            head.weight.mul_(6.0)
        for per_component in model.compositors:
            for comp in per_component:
                comp.net[-1].weight.mul_(8.0)
    return model


@pytest.mark.parametrize(
    "config",
    [
        dict(components="surface_volume", filter_space="linear", transform="log_modulus"),
        dict(components="surface_volume", filter_space="transformed", conv_kernel=5, kernel_size=5),
        dict(components="color", filter_space="linear", transform="none"),
        dict(components="color", filter_space="transformed", transform="none"),
    ],
)
def test_the_forward_pass_equals_an_independent_multiscale_reference(config):
    """Every scale's kernel on its pyramid level, each scale's compositor, the per-component heads, the
    padding and crop (14 x 10 is padded to 16 x 12): the model's output equals the reference, and the
    references with two compositors, the component kernels, or the pyramid swapped differ from it."""
    model = sharpened(tiny(**config))
    batch = varied_frame_batch(14, 10)
    with torch.no_grad():
        out = model(batch)["color"]
        expected = reference_forward(model, batch)
        by_scale = [[(c, 1), (c, 0)] for c in range(len(model.compositors))]
        variants = {
            "scale compositors swapped": reference_forward(model, batch, compositor_of=by_scale),
            "pyramid of filtered levels": reference_forward(model, batch, pyramid_of_filtered=True),
        }
        if model.components == "surface_volume":
            variants["component kernels swapped"] = reference_forward(model, batch, kernel_of=[1, 0])
            variants["component compositors swapped"] = reference_forward(
                model, batch, compositor_of=[[(1, 0), (1, 1)], [(0, 0), (0, 1)]]
            )
    assert out.shape == (2, 3, 14, 10) and out.dtype == torch.float64
    torch.testing.assert_close(out, expected, atol=1e-9, rtol=1e-9)
    for name, variant in variants.items():
        assert (variant - expected).abs().max() > 1e-3, name


def test_one_scale_of_width_one_is_one_softmax_kernel_on_the_linear_colour():
    """widths=[1]: no pooling, no compositor; the output is the kernel-filtered inverse-transformed colour."""
    model = sharpened(tiny(widths=[1]))
    batch = varied_frame_batch(5, 7)
    assert [len(c) for c in model.compositors] == [0]
    with torch.no_grad():
        out = model(batch)["color"]
        scores = model.heads[0](model.encoder[0](batch["radiance_in"]))
    expected = _softmax_filter(scores, _inverse_lm(batch["radiance_t"]), 3)
    torch.testing.assert_close(out, expected, atol=1e-9, rtol=1e-9)
    torch.testing.assert_close(out, reference_forward(model, batch), atol=1e-9, rtol=1e-9)


def test_there_is_one_compositor_per_component_and_scale_but_the_coarsest():
    """S - 1 compositors per component (an extra one would be an unused parameter set in checkpoints)."""
    for components, n in (("color", 1), ("surface_volume", 2)):
        model = tiny(components=components)
        assert [len(c) for c in model.compositors] == [2] * n
        compositor = sum(p.numel() for p in model.compositors[0][0].parameters())
        assert compositor == (6 * 9 + 1) * 4 + (4 + 1)  # 3x3 conv 6 -> 4 channels, 1x1 conv 4 -> 1
        others = sum(p.numel() for m in (model.encoder, model.decoder, model.heads) for p in m.parameters())
        assert sum(p.numel() for p in model.parameters()) == others + 2 * n * compositor


def test_a_compositor_with_a_5x5_conv_is_a_same_size_sigmoid_of_two_convolutions():
    torch.manual_seed(3)
    compositor = ScaleCompositor(4, conv_kernel=5, channels=2).double()
    g = torch.Generator().manual_seed(4)
    coarse_up, fine = (torch.randn(1, 2, 6, 5, generator=g, dtype=torch.float64) for _ in range(2))
    with torch.no_grad():
        a = compositor(coarse_up, fine)
        assert a.shape == (1, 1, 6, 5) and compositor.radius == 2
        torch.testing.assert_close(a, _compositor(compositor, coarse_up, fine), atol=1e-12, rtol=1e-12)
        swapped = _compositor(compositor, fine, coarse_up)  # [f, U(c)] instead of [U(c), f]
    assert (swapped - a).abs().max() > 1e-3


def test_the_kernel_and_composition_flops_are_summed_over_scales_by_pixel_fraction():
    """Closed form for k = 3 over three scales: kernels at 1, 1/4, 1/16 of the pixels, pyramid levels
    built from 1 and 1/4, compositions at 1 and 1/4; per component. One scale: one kernel application."""
    kernel = 2 * 9 * 3 + SOFTMAX_FLOPS_PER_TAP * 9
    per_component = kernel * (1 + 1 / 4 + 1 / 16) + PYRAMID_FLOPS * (1 + 1 / 4) + COMPOSE_FLOPS * (1 + 1 / 4)
    assert tiny().kernel_flops_per_pixel() == pytest.approx(per_component, rel=1e-12)
    assert tiny(components="surface_volume").kernel_flops_per_pixel() == pytest.approx(2 * per_component)
    assert tiny(widths=[4]).kernel_flops_per_pixel() == pytest.approx(kernel, rel=1e-12)


@pytest.mark.parametrize(
    ("key", "value", "needles"),
    [
        ("in_channels", 0, ["model.in_channels", ">= 1"]),
        ("convs_per_level", 0, ["model.convs_per_level", ">= 1"]),
        ("conv_kernel", 4, ["model.conv_kernel", "odd"]),
        ("compositor_width", 0, ["model.compositor_width", ">= 1"]),
        ("components", "diffuse", ["model.components", "surface_volume"]),
        ("filter_space", "log", ["model.filter_space", "transformed"]),
    ],
)
def test_a_bad_value_passed_to_the_constructor_is_a_one_line_config_error(key, value, needles):
    """The constructor's own checks (build_method's type checks already refuse a bad Literal)."""
    with pytest.raises(ConfigError) as excinfo:
        tiny(**{key: value})
    one_line_error(excinfo, *needles)


# --- the KPCN family on the one radiance branch (models.py with branches: [radiance]) -----------------


def _radiance_model(output):
    torch.manual_seed(5)
    model = conv_stack_denoiser(
        in_channels=IN, width=4, depth=2, conv_kernel=3, output=output, kernel_size=3, shared=False,
        whiten=False, branches=["radiance"],
    )  # fmt: skip
    return model.double().eval()


@pytest.mark.parametrize("transform", ["log_modulus", "none"])
def test_the_radiance_kpcn_filters_the_transformed_colour_and_the_dpcn_outputs_it_both_inverted(transform):
    """KPCN: inverse(softmax kernel * radiance_t); DPCN: inverse(network output), the inverse being the
    sequences' colour space. The surface/volume parts of the batch must not matter."""
    batch = varied_frame_batch(6, 5)
    inverse = _inverse_lm if transform == "log_modulus" else (lambda t: t)
    space = RadianceTransform(transform)
    kpcn, dpcn = _radiance_model("kernel"), _radiance_model("direct")
    with torch.no_grad():
        scores, direct = kpcn.radiance_net(batch["radiance_in"]), dpcn.radiance_net(batch["radiance_in"])
        expected = inverse(_softmax_filter(scores, batch["radiance_t"], 3))
        torch.testing.assert_close(final_color(kpcn(batch), batch, space), expected, atol=1e-12, rtol=1e-12)
        torch.testing.assert_close(
            final_color(dpcn(batch), batch, space), inverse(direct), atol=1e-12, rtol=1e-12
        )
    assert (expected - inverse(batch["radiance_t"])).abs().max() > 1e-2  # the kernel does filter


def test_the_radiance_models_halo_and_kernel_cost_count_one_branch_and_the_kernel_only_for_kernel_output():
    kpcn, dpcn = _radiance_model("kernel"), _radiance_model("direct")
    assert dpcn.halo == 2 and kpcn.halo == 2 + 1  # two 3x3 convs; + the 3x3 kernel's radius
    assert dpcn.kernel_size is None and dpcn.kernel_flops_per_pixel() == 0
    assert kpcn.kernel_flops_per_pixel() == 2 * 9 * 3 + SOFTMAX_FLOPS_PER_TAP * 9  # one branch, not two
    assert [name for name, _ in kpcn.named_children()] == ["radiance_net"]


def test_a_radiance_batch_of_the_wrong_shape_or_without_the_branch_is_a_one_line_data_error():
    from src.errors import DataError

    kpcn = _radiance_model("kernel")
    batch = varied_frame_batch(6, 5)
    for bad in (batch["radiance_in"][:, :4], batch["radiance_in"][0]):  # 4 of 5 channels; no batch axis
        with pytest.raises(DataError) as excinfo:
            kpcn(batch | {"radiance_in": bad})
        one_line_error(excinfo, "batch['radiance_in'] is", f"expected (N, {IN}, H, W)")
    with pytest.raises(DataError) as excinfo:
        tiny()({"radiance_t": batch["radiance_t"]})
    one_line_error(excinfo, "batch has no 'radiance_in'", "radiance branch")


# Surviving mutants of src/models/denoise/unet_kpcn.py (bash scripts/mutation.sh unet_kpcn), all
# equivalent here:
# - _conv_block and ScaleCompositor `nn.ReLU(inplace=True)` -> inplace None / False: the same values (in
#   place only saves the copy).
# - pad_to_multiple `if dy or dx` -> `... or True`: F.pad by zero pixels returns the input unchanged.
# - pad_to_multiple and forward `x.shape[-2:]` -> `x.shape[+2:]`: the frames are (N, C, H, W)
#   (branch_input refuses any other rank), so both are (H, W).
# - upsample `mode="nearest"` dropped: nearest is F.interpolate's default mode.
# - filter_scales and kernel_logits `zip(..., strict=True)` -> strict None / False / dropped: both lists
#   have one entry per scale by construction (heads and features, logits and the pyramid).
