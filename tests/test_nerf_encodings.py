"""Radiance-field encodings as objects (src/models/nerf/encodings.py): each one's `out_dim` against its
closed form and its output, each class against the pure function it wraps (whose own closed-form and
Monte Carlo tests are in tests/test_nerf_math.py), what each reads, the one-line errors of a bad
`model.<position|view>_encoding`, the upgrade of the flat keys of older checkpoints, and a user's own
encoding (tests/plugins/toy_encoding.py with tests/conf/model/toy_encoding_nerf.yaml): one class and one
YAML, built, run, trained and evaluated."""

import copy
import inspect
import json
import math
import subprocess

import pytest
import torch

from src.errors import ConfigError, DataError
from src.models.instantiate import build_method
from src.models.nerf.builders import upgrade_legacy_encodings
from src.models.nerf.directional import integrated_dir_enc, l2_normalize, reflect
from src.models.nerf.encodings import (
    READS,
    IntegratedDirectionalEncoding,
    IntegratedPositionalEncoding,
    PositionalEncoding,
    cast_rays,
    integrated_pos_enc,
    pos_enc,
)
from src.models.nerf.fields import RefNerfMLP
from src.models.nerf.models import interval_inputs, point_inputs
from src.models.parameters import count_parameters
from src.train.checkpoint import load_checkpoint
from tests.conftest import (
    ROOT,
    assert_loads_from_legacy_checkpoint,
    cli_job,
    one_line_cli_error,
    one_line_error,
)
from tests.plugins.toy_encoding import RandomFourierFeatures
from tests.test_nerf_models import model_cfg, sphere_scene

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py

F64 = torch.float64
TOY = ["model=toy_encoding_nerf", "hydra.searchpath=[file://tests/conf]"]


def points(*shape: int, seed: int = 0) -> torch.Tensor:
    return torch.randn(*shape, 3, generator=torch.Generator().manual_seed(seed), dtype=F64)


# --- out_dim against the closed forms, and against the output ------------------------------------------


@pytest.mark.parametrize(
    ("min_deg", "max_deg", "identity", "expected"),
    [(0, 10, True, 63), (0, 4, True, 27), (2, 5, False, 18), (3, 4, True, 9)],
)
def test_positional_encoding_out_dim(min_deg, max_deg, identity, expected):
    """3 (2 (max_deg - min_deg) + identity): NeRF's 63 (L = 10) and 27 (L = 4)."""
    enc = PositionalEncoding(min_deg, max_deg, identity)
    assert enc.out_dim == expected == 3 * (2 * (max_deg - min_deg) + identity)
    assert enc(points(2, 5)).shape == (2, 5, expected)


@pytest.mark.parametrize(("min_deg", "max_deg", "expected"), [(0, 16, 96), (0, 10, 60), (2, 5, 18)])
def test_integrated_positional_encoding_out_dim(min_deg, max_deg, expected):
    """2 x 3 (max_deg - min_deg), no identity term: mip-NeRF's 96 (degrees 0-15)."""
    enc = IntegratedPositionalEncoding(min_deg, max_deg)
    assert enc.out_dim == expected == 6 * (max_deg - min_deg)
    assert enc(points(4), points(4, seed=1).abs()).shape == (4, expected)


@pytest.mark.parametrize(("deg_view", "expected"), [(1, 4), (2, 10), (3, 20), (5, 72)])
def test_integrated_directional_encoding_out_dim(deg_view, expected):
    """2 sum_l (l + 1) over l = 1, 2, ..., 2^(deg_view - 1), i.e. 2 (2^deg_view - 1 + deg_view):
    Ref-NeRF's 72 (deg_view 5)."""
    enc = IntegratedDirectionalEncoding(deg_view)
    assert enc.out_dim == expected == 2 * (2**deg_view - 1 + deg_view)
    assert enc(l2_normalize(points(3)), torch.full((3, 1), 0.1, dtype=F64)).shape == (3, expected)


# --- the classes are the pure functions -----------------------------------------------------------------


def test_the_classes_compute_the_pure_functions():
    """Settings away from the defaults (min_deg > 0, identity off), so that a class passing its degrees
    in the wrong order, dropping min_deg or ignoring identity gives other features."""
    x, var = points(4, 6), points(4, 6, seed=1) ** 2
    for min_deg, max_deg, identity in ((2, 5, False), (1, 4, True)):
        assert torch.equal(
            PositionalEncoding(min_deg, max_deg, identity)(x), pos_enc(x, min_deg, max_deg, identity)
        )
        assert torch.equal(
            IntegratedPositionalEncoding(min_deg, max_deg)(x, var),
            integrated_pos_enc(x, var, min_deg, max_deg),
        )
    dirs, kappa_inv = l2_normalize(x), var[..., :1]
    for deg_view in (2, 4):
        assert torch.equal(
            IntegratedDirectionalEncoding(deg_view)(dirs, kappa_inv),
            integrated_dir_enc(dirs, kappa_inv, deg_view),
        )


def test_each_encoding_reads_what_its_forward_takes():
    """`reads` names the inputs a model computes for it (`READS`): the arguments of `forward`, in order."""
    for enc, reads in (
        (PositionalEncoding(0, 2), "point"),
        (IntegratedPositionalEncoding(0, 2), "gaussian"),
        (IntegratedDirectionalEncoding(2), "vmf"),
        (RandomFourierFeatures(4, 1.0), "point"),
    ):
        assert enc.reads == reads
        assert tuple(inspect.signature(enc.forward).parameters) == READS[reads]


@pytest.mark.parametrize(
    ("cls", "args", "needle"),
    [
        (PositionalEncoding, (0, 0), "max_deg: expected > min_deg (0), got 0"),
        (PositionalEncoding, (-1, 4), "min_deg: expected >= 0, got -1"),
        (IntegratedPositionalEncoding, (3, 2), "max_deg: expected > min_deg (3), got 2"),
        (IntegratedDirectionalEncoding, (6,), "deg_view: expected an integer in [1, 5]"),
        (IntegratedDirectionalEncoding, (0,), "deg_view: expected an integer in [1, 5]"),
    ],
)
def test_settings_out_of_range_are_refused(cls, args, needle):
    with pytest.raises(ValueError) as excinfo:
        cls(*args)
    one_line_error(excinfo, needle)


# --- the models take their sizes and inputs from the encodings ------------------------------------------


@pytest.mark.parametrize(
    ("name", "position", "view"),
    [("nerf", (0, 10, True), (0, 4, True)), ("mipnerf", (0, 16), (0, 4, True)), ("refnerf", (0, 16), (5,))],
)
def test_the_paper_configs_build_the_paper_encodings(name, position, view):
    model = build_method(model_cfg(name))
    mlp = model.mlp_for(0)
    if name == "refnerf":
        pos_enc_, view_enc = mlp.position_encoding, mlp.view_encoding
        assert isinstance(view_enc, IntegratedDirectionalEncoding) and (view_enc.deg_view,) == view
    else:
        pos_enc_, view_enc = model.position_encoding, model.view_encoding
        assert isinstance(view_enc, PositionalEncoding)
        assert (view_enc.min_deg, view_enc.max_deg, view_enc.identity) == view
    if name == "nerf":
        assert isinstance(pos_enc_, PositionalEncoding)
        assert (pos_enc_.min_deg, pos_enc_.max_deg, pos_enc_.identity) == position
    else:
        assert type(pos_enc_) is IntegratedPositionalEncoding
        assert (pos_enc_.min_deg, pos_enc_.max_deg) == position
    assert mlp.trunk.layers[0].in_features == pos_enc_.out_dim


def test_refnerf_mlp_without_encodings_given_takes_the_papers():
    mlp = RefNerfMLP(depth=1, width=4, bottleneck_width=4, view_depth=1, view_width=4, view_skip_layer=None)
    assert (mlp.position_encoding.min_deg, mlp.position_encoding.max_deg) == (0, 16)
    assert mlp.view_encoding.deg_view == 5 and mlp.trunk.layers[0].in_features == 96
    assert mlp.view_mlp.layers[0].in_features == 4 + 72 + 1


def test_a_profile_changes_an_encoding_setting_and_the_mlp_follows():
    """conf/model_profile/mipnerf_cpu.yaml sets `position_encoding: {max_deg: 10}`: IPE degrees 0-9, 60
    features into the trunk (and its skip)."""
    model = build_method(model_cfg("mipnerf", "cpu"))
    assert (model.position_encoding.min_deg, model.position_encoding.max_deg) == (0, 10)
    assert [layer.in_features for layer in model.mlp_for(0).trunk.layers][:1] == [60]


def test_an_encoding_file_is_chosen_from_the_command_line():
    """`encoding@model.position_encoding=mipnerf_position` (docs): NeRF on the frustums' IPE, 96 inputs,
    and the model then computes the Gaussians for it."""
    cfg = model_cfg("nerf", "smoke", "encoding@model.position_encoding=mipnerf_position")
    model = build_method(cfg)
    assert type(model.position_encoding) is IntegratedPositionalEncoding
    assert model.mlp_for(0).trunk.layers[0].in_features == 96
    rays, _ = sphere_scene(n_side=2)
    assert set(model.sample_inputs(rays, torch.linspace(2, 4, 5).expand(4, 5))[1]) == {"means", "covs"}


def _recorded(encoding: torch.nn.Module) -> list:
    """The (args, kwargs) of every call of `encoding`, appended as it is called."""
    calls = []
    encoding.register_forward_pre_hook(lambda _, args, kwargs: calls.append((args, kwargs)), with_kwargs=True)
    return calls


def test_the_models_feed_each_encoding_what_it_reads():
    """NeRF: the interval midpoints to the position encoding, the unit view directions (not the ray
    directions) to the view encoding; mip-NeRF: each interval's frustum Gaussian (`cast_rays`); Ref-NeRF:
    the Gaussians, and the reflected view direction with the sample's roughness to its IDE."""
    rays, _ = sphere_scene(n_side=3)
    rays["directions"] = 2.5 * rays["directions"]  # not unit: the view directions differ from them
    torch.manual_seed(0)
    nerf = build_method(model_cfg("nerf", "smoke"))
    position, view = _recorded(nerf.position_encoding), _recorded(nerf.view_encoding)
    with torch.no_grad():
        out = nerf(rays, randomized=False)
    t = out[0]["tdist"]
    midpoints = (
        rays["origins"][:, None] + (0.5 * (t[:, 1:] + t[:, :-1]))[..., None] * rays["directions"][:, None]
    )
    args, kwargs = position[0]
    assert args == () and set(kwargs) == {"x"} and torch.equal(kwargs["x"], midpoints)
    assert len(view) == 2 and all(torch.equal(args[0], rays["viewdirs"]) and not kw for args, kw in view)

    mip = build_method(model_cfg("mipnerf", "smoke"))
    position = _recorded(mip.position_encoding)
    with torch.no_grad():
        out = mip(rays, randomized=False)
    means, covs = cast_rays(out[1]["tdist"], rays["origins"], rays["directions"], rays["radii"])
    assert set(position[1][1]) == {"means", "covs"}
    assert torch.equal(position[1][1]["means"], means) and torch.equal(position[1][1]["covs"], covs)

    ref = build_method(model_cfg("refnerf", "smoke")).mlp_for(0)
    position, view = _recorded(ref.position_encoding), _recorded(ref.view_encoding)
    means, covs = cast_rays(out[1]["tdist"], rays["origins"], rays["directions"], rays["radii"])
    fields = ref({"means": means, "covs": covs}, rays["viewdirs"])
    assert torch.equal(position[0][1]["means"], means) and torch.equal(position[0][1]["covs"], covs)
    d = rays["viewdirs"][:, None].expand_as(fields["normals_pred"])
    (directions, kappa_inv), _ = view[0]
    assert torch.equal(directions, reflect(-d, fields["normals_pred"]))
    assert torch.equal(kappa_inv, fields["roughness"][..., None])


@pytest.mark.parametrize("name", ["nerf", "mipnerf", "refnerf"])
def test_the_density_of_a_point_is_the_encoding_of_the_point(name):
    """An occupancy grid's query (`point_density`): NeRF's PE of the point; for the IPE (mip-NeRF,
    Ref-NeRF) a Gaussian of zero covariance, i.e. the PE of the point without the identity term."""
    torch.manual_seed(0)
    model = build_method(model_cfg(name, "smoke"))
    p = 0.3 * points(7).float()
    mlp = model.mlp_for(1)
    with torch.no_grad():
        if name == "nerf":
            expected = mlp.density(pos_enc(p, 0, 10, append_identity=True))
        elif name == "mipnerf":
            expected = mlp.density(pos_enc(p, 0, 16, append_identity=False))
        else:  # RefNerfMLP's spatial trunk and density head, by hand
            raw = mlp.density_head(mlp.trunk(pos_enc(p, 0, 16, append_identity=False)))[..., 0]
            expected = mlp.density_act(raw + mlp.density_bias)
        torch.testing.assert_close(model.point_density(p), expected, rtol=1e-5, atol=1e-6)
    assert point_inputs("point", p) == {"x": p}
    with pytest.raises(ValueError, match="'vmf'"):
        point_inputs("vmf", p)
    rays, _ = sphere_scene(n_side=2)
    with pytest.raises(ValueError, match="'vmf'"):  # not a position encoding's input
        interval_inputs("vmf", rays, torch.linspace(2, 4, 5).expand(4, 5))


# --- errors ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "key", "target", "needles"),
    [
        ("nerf", "position_encoding", "torch.nn.ReLU", ["'torch.nn.ReLU' is not an encoding"]),
        ("nerf", "view_encoding", "src.models.nerf.encodings.pos_enc", ["pos_enc' is not an encoding"]),
        ("refnerf", "position_encoding", "src.models.nerf.encodings.Encoding", ["Encoding sets no out_dim"]),
        ("refnerf", "view_encoding", None, ["expected the dotted path of a class"]),
        ("mipnerf", "position_encoding", "src.models.nerf.encodings.NoSuchEncoding", ["cannot import"]),
    ],
)
def test_a_target_that_is_not_an_encoding_is_a_one_line_error(name, key, target, needles):
    cfg = model_cfg(name, "smoke")
    cfg[key] = {"_target_": target} if target else {"deg_view": 5}
    with pytest.raises(ConfigError) as excinfo:
        build_method(cfg)
    one_line_error(excinfo, f"model.{key}._target_", *needles)


@pytest.mark.parametrize(
    ("name", "key", "encoding", "reads"),
    [
        (
            "nerf",
            "view_encoding",
            {"_target_": "src.models.nerf.encodings.IntegratedPositionalEncoding"},
            "gaussian",
        ),
        (
            "mipnerf",
            "position_encoding",
            {"_target_": "src.models.nerf.encodings.IntegratedDirectionalEncoding"},
            "vmf",
        ),
        ("refnerf", "view_encoding", {"_target_": "src.models.nerf.encodings.PositionalEncoding"}, "point"),
    ],
)
def test_an_encoding_that_reads_the_wrong_input_for_its_place_is_a_one_line_error(name, key, encoding, reads):
    """NeRF's view encoding reads the view direction (a point); a position encoding a point or a
    Gaussian; Ref-NeRF's view encoding a vMF lobe (reflected direction and roughness)."""
    cfg = model_cfg(name, "smoke")
    settings = {"deg_view": 2} if reads == "vmf" else {"min_deg": 0, "max_deg": 2}
    cfg[key] = encoding | settings
    with pytest.raises(ConfigError) as excinfo:
        build_method(cfg)
    one_line_error(excinfo, f"model.{key}._target_", f"reads {reads!r}")


def test_an_encoding_that_is_not_a_mapping_is_a_one_line_error():
    cfg = model_cfg("nerf", "smoke")
    cfg["position_encoding"] = 10
    with pytest.raises(ConfigError) as excinfo:
        build_method(cfg)
    one_line_error(excinfo, "model.position_encoding:", "expected a mapping with _target_", "got 10")


def test_the_cli_exits_2_naming_the_encoding_target(tmp_path):
    args = ["task=nerf", "model=nerf", "profile=smoke", "stage=summary", f"hydra.run.dir={tmp_path}/run"]
    cmd, env = cli_job([*args, "model.position_encoding._target_=torch.nn.ReLU"], tmp_path / "data")
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    one_line_cli_error(result, "model.position_encoding._target_", "'torch.nn.ReLU' is not an encoding")


# --- configs and checkpoints from before the encodings were sub-configs -----------------------------------

#: The flat keys each paper config had before `position_encoding` / `view_encoding`.
LEGACY_KEYS = {
    "nerf": {
        "pos_min_deg": 0,
        "pos_max_deg": 10,
        "pos_identity": True,
        "view_min_deg": 0,
        "view_max_deg": 4,
        "view_identity": True,
    },
    "mipnerf": {
        "pos_min_deg": 0,
        "pos_max_deg": 16,
        "view_min_deg": 0,
        "view_max_deg": 4,
        "view_identity": True,
    },
    "refnerf": {"pos_min_deg": 0, "pos_max_deg": 16, "deg_view": 5},
}


PE, IPE = (
    "src.models.nerf.encodings.PositionalEncoding",
    "src.models.nerf.encodings.IntegratedPositionalEncoding",
)
IDE = "src.models.nerf.encodings.IntegratedDirectionalEncoding"
#: Flat keys with every value distinct (and off the paper's), and the sub-configs they mean: a key read
#: into the wrong place, or a paper value written in, gives another config.
DISTINCT = {
    "nerf": (
        {"pos_min_deg": 1, "pos_max_deg": 9, "pos_identity": False}
        | {"view_min_deg": 2, "view_max_deg": 5, "view_identity": True},
        {"_target_": PE, "min_deg": 1, "max_deg": 9, "identity": False},
        {"_target_": PE, "min_deg": 2, "max_deg": 5, "identity": True},
    ),
    "mipnerf": (
        {"pos_min_deg": 3, "pos_max_deg": 11, "view_min_deg": 1, "view_max_deg": 3, "view_identity": False},
        {"_target_": IPE, "min_deg": 3, "max_deg": 11},
        {"_target_": PE, "min_deg": 1, "max_deg": 3, "identity": False},
    ),
    "refnerf": (
        {"pos_min_deg": 2, "pos_max_deg": 12, "deg_view": 3},
        {"_target_": IPE, "min_deg": 2, "max_deg": 12},
        {"_target_": IDE, "deg_view": 3},
    ),
}


@pytest.mark.parametrize("name", sorted(LEGACY_KEYS))
def test_a_config_with_the_old_flat_encoding_keys_upgrades_to_todays(name):
    cfg = model_cfg(name)
    rest = {k: v for k, v in cfg.items() if not k.endswith("_encoding")}
    assert upgrade_legacy_encodings(rest | LEGACY_KEYS[name]) == cfg  # the paper's
    flat, position, view = DISTINCT[name]
    upgraded = upgrade_legacy_encodings(rest | flat)
    assert upgraded == rest | {"position_encoding": position, "view_encoding": view}
    build_method(upgraded)  # a config today's builders take
    assert upgrade_legacy_encodings(cfg) == cfg  # today's config is left as it is


def test_a_checkpoint_with_the_old_flat_encoding_keys_still_loads(tmp_path):
    cfg = model_cfg("mipnerf", "cpu")  # the cpu profile's IPE degrees 0-9, not the paper's
    legacy = {k: v for k, v in cfg.items() if not k.endswith("_encoding")} | LEGACY_KEYS["mipnerf"]
    legacy["pos_max_deg"] = 10
    assert_loads_from_legacy_checkpoint(cfg, legacy, tmp_path / "old.pt")
    legacy["pos_max_deg"] = 16  # a different network: refused, naming the key
    with pytest.raises(DataError) as excinfo:
        assert_loads_from_legacy_checkpoint(cfg, legacy, tmp_path / "other.pt")
    one_line_error(excinfo, "model.position_encoding")


# --- a user's own encoding: one class, one YAML -----------------------------------------------------------


def test_a_users_encoding_is_one_class_and_one_yaml():
    """tests/conf/model/toy_encoding_nerf.yaml inherits conf/model/nerf.yaml and swaps the position
    encoding for tests/plugins/toy_encoding.py's random Fourier features: only its own keys reach the
    class, the MLPs take its out_dim (64 against the PE's 63), the model feeds it the interval midpoints,
    and it renders."""
    cfg = model_cfg("toy_encoding_nerf", "smoke", "task=nerf", *TOY[1:])
    assert cfg["position_encoding"] == {
        "_target_": "tests.plugins.toy_encoding.RandomFourierFeatures",
        "num_features": 32,
        "scale": 2.0,
        "seed": 0,
    }
    nerf_cfg = model_cfg("nerf", "smoke", "task=nerf")
    assert {k: v for k, v in cfg.items() if k not in ("name", "position_encoding")} == {
        k: v for k, v in nerf_cfg.items() if k not in ("name", "position_encoding")
    }
    torch.manual_seed(0)
    model = build_method(cfg)
    enc = model.position_encoding
    assert isinstance(enc, RandomFourierFeatures) and enc.out_dim == 64
    # The trunk's first layer and the layers after its skip take 64 inputs: two MLPs of
    # (width + 1 (density head) + bottleneck_width) more weights than NeRF's.
    assert model.mlp_for(0).trunk.layers[0].in_features == 64
    extra = 2 * (cfg["width"] + 1 + cfg["bottleneck_width"])
    assert count_parameters(model) == count_parameters(build_method(nerf_cfg)) + extra
    # gamma(x) = [cos(2 pi B x), sin(2 pi B x)], B drawn from N(0, scale^2) with the seed (and saved).
    x = points(5).float()
    b = 2.0 * torch.randn(32, 3, generator=torch.Generator().manual_seed(0))
    expected = torch.cat([torch.cos(2 * math.pi * x @ b.T), torch.sin(2 * math.pi * x @ b.T)], dim=-1)
    torch.testing.assert_close(model.encode_positions({"x": x}), expected)
    assert torch.equal(model.state_dict()["position_encoding.freqs"], b)
    rays, _ = sphere_scene(n_side=4)
    outputs = model(rays, randomized=True, generator=torch.Generator().manual_seed(1))
    assert outputs[-1]["rgb"].shape == (16, 3) and bool(torch.isfinite(outputs[-1]["rgb"]).all())
    t_mid = 0.5 * (outputs[0]["tdist"][..., 1:] + outputs[0]["tdist"][..., :-1])
    midpoints = rays["origins"][:, None] + t_mid[..., None] * rays["directions"][:, None]
    assert torch.equal(model.sample_inputs(rays, outputs[0]["tdist"])[1]["x"], midpoints)


@pytest.mark.slow
def test_a_users_encoding_trains_and_evaluates_through_the_cli(tmp_path, mitsuba_variant):
    """`python -m src.run task=nerf model=toy_encoding_nerf hydra.searchpath=[file://tests/conf]
    profile=smoke`: rendered, trained, evaluated and reported; its checkpoint holds the encoding's
    frequencies and reloads into the model its config builds."""
    run_dir = tmp_path / "run"
    cmd, env = cli_job(["task=nerf", *TOY, "profile=smoke", f"hydra.run.dir={run_dir}"], tmp_path / "data")
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    checkpoint = load_checkpoint(run_dir / "checkpoints" / "final.pt")
    assert checkpoint["step"] == 30 and checkpoint["model_config"]["name"] == "toy_encoding_nerf"
    assert checkpoint["model"]["position_encoding.freqs"].shape == (32, 3)
    metrics = json.loads((run_dir / "eval" / "metrics.json").read_text())
    assert metrics["model"] == "toy_encoding_nerf" and 5 < metrics["mean"]["psnr"] < 40
    assert (tmp_path / "data" / "reports" / "nerf" / "index.html").is_file()
    model = build_method(copy.deepcopy(checkpoint["model_config"]))
    model.load_state_dict(checkpoint["model"])
