"""LPIPS (src/metrics/lpips.py) against the `lpips` package as an oracle, and FLIP (src/metrics/flip.py)."""

from pathlib import Path

import numpy as np
import pytest
import torch

from src.errors import ConfigError
from src.metrics.flip import flip
from src.metrics.image import image_metrics, lpips_variant, tonemap
from src.metrics.lpips import LPIPS, lpips_distance
from tests.conftest import compose_config, one_line_error

# The package builds its (random) trunk with torchvision's deprecated `pretrained=` argument.
pytestmark = pytest.mark.filterwarnings("ignore:.*(pretrained|weight enum).*:UserWarning")

lpips_pkg = pytest.importorskip("lpips")
LIN_V01 = Path(lpips_pkg.__file__).parent / "weights" / "v0.1" / "vgg.pth"


def _package_model(lin: bool):
    """The package's VGG LPIPS with a random trunk (no download) and, if `lin`, the bundled v0.1 weights."""
    torch.manual_seed(123)
    return lpips_pkg.LPIPS(net="vgg", pretrained=True, pnet_rand=True, lpips=lin, verbose=False).eval()


def _trunk_file(pkg_model, path: Path) -> Path:
    """The package's trunk as a full torchvision VGG16 state dict (`features.N.*` keys)."""
    state = {}
    for i in range(1, 6):
        for name, value in getattr(pkg_model.net, f"slice{i}").state_dict().items():
            state[f"features.{name}"] = value.clone()  # slice modules keep the features index as name
    torch.save(state, path)
    return path


@pytest.fixture(scope="module")
def oracle(tmp_path_factory):
    """(package LPIPS, package baseline, trunk file) sharing one random trunk."""
    pkg = _package_model(lin=True)
    base = _package_model(lin=False)
    base.net.load_state_dict(pkg.net.state_dict())
    path = _trunk_file(pkg, tmp_path_factory.mktemp("lpips") / "vgg16_trunk.pth")
    return pkg, base, path


@pytest.fixture(scope="module")
def random_model():
    return LPIPS(seed=0)


def _images(seed=0, n=2, h=64, w=48):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 3, h, w, generator=g) * 2 - 1, torch.rand(n, 3, h, w, generator=g) * 2 - 1


def test_identical_images_give_zero(random_model):
    x, _ = _images()
    with torch.no_grad():
        d = random_model(x, x)
    assert d.shape == (2,)
    assert torch.all(d.abs() < 1e-6)
    assert random_model.variant == "vgg16-random(seed=0)+lin-uniform"


def test_matches_the_lpips_package_with_v01_weights(oracle):
    pkg, _, trunk = oracle
    ours = LPIPS(trunk_weights=trunk, lin_weights=LIN_V01)
    assert ours.variant == "vgg16-file(vgg16_trunk.pth)+lin-v0.1(vgg.pth)"
    x, y = _images(1)
    with torch.no_grad():
        expected = pkg(x, y).flatten()
        got = ours(x, y)
    assert torch.all(expected > 0)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-7)


def test_baseline_matches_the_package_without_linear_layers(oracle):
    _, base, trunk = oracle
    ours = LPIPS(trunk_weights=trunk)
    assert ours.variant == "vgg16-file(vgg16_trunk.pth)+lin-uniform"
    x, y = _images(2)
    with torch.no_grad():
        expected = base(x, y).flatten()
        got = ours(x, y)
    torch.testing.assert_close(got, expected, rtol=1e-5, atol=1e-7)


def test_features_only_state_dict_is_accepted(oracle, tmp_path):
    pkg, _, trunk = oracle
    full = torch.load(trunk)
    path = tmp_path / "features_only.pth"
    torch.save({k.removeprefix("features."): v for k, v in full.items()}, path)
    x, y = _images(3)
    with torch.no_grad():
        torch.testing.assert_close(LPIPS(trunk_weights=path)(x, y), LPIPS(trunk_weights=trunk)(x, y))


def test_random_trunk_is_deterministic_and_leaves_global_rng_alone(random_model):
    x, y = _images(4)
    state = torch.random.get_rng_state()
    same, other = LPIPS(seed=0), LPIPS(seed=1)
    assert torch.equal(torch.random.get_rng_state(), state)
    with torch.no_grad():
        assert torch.equal(random_model(x, y), same(x, y))
        assert not torch.allclose(random_model(x, y), other(x, y))
    assert other.variant == "vgg16-random(seed=1)+lin-uniform"
    assert not any(p.requires_grad for p in random_model.parameters())
    assert not random_model.train().training


def test_bad_weight_files_are_one_line_config_errors(tmp_path):
    with pytest.raises(ConfigError) as excinfo:
        LPIPS(trunk_weights=tmp_path / "missing.pth")
    one_line_error(excinfo, "metrics.lpips.trunk_weights", "missing.pth")
    wrong = tmp_path / "wrong.pth"
    torch.save({"foo.weight": torch.zeros(1)}, wrong)
    with pytest.raises(ConfigError) as excinfo:
        LPIPS(trunk_weights=wrong)
    one_line_error(excinfo, "metrics.lpips.trunk_weights", "wrong.pth", "0.weight")
    with pytest.raises(ConfigError) as excinfo:
        LPIPS(lin_weights=wrong)
    one_line_error(excinfo, "metrics.lpips.lin_weights", "lin0.model.1.weight")
    with pytest.raises(ConfigError) as excinfo:
        LPIPS(lin_weights=tmp_path / "nope.pth")
    one_line_error(excinfo, "metrics.lpips.lin_weights", "nope.pth")


def test_lpips_distance_maps_zero_one_to_minus_one_one(random_model):
    rng = np.random.default_rng(5)
    a, b = rng.uniform(0, 1, (32, 40, 3)), rng.uniform(0, 1, (32, 40, 3))
    ta = torch.from_numpy(a).float().permute(2, 0, 1)[None] * 2 - 1
    tb = torch.from_numpy(b).float().permute(2, 0, 1)[None] * 2 - 1
    with torch.no_grad():
        expected = float(random_model(ta, tb)[0])
    assert lpips_distance(random_model, a, b) == pytest.approx(expected, rel=1e-6)
    assert lpips_distance(random_model, a, a) == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize("mode", ["hdr", "ldr"])
def test_flip_zero_for_identical_and_positive_for_different(mode):
    rng = np.random.default_rng(6)
    high = 4.0 if mode == "hdr" else 1.0
    ref = rng.uniform(0, high, (24, 32, 3))
    assert flip(ref, ref, mode) == pytest.approx(0.0, abs=1e-7)
    test = np.clip(ref + rng.normal(0, 0.2 * high, ref.shape), 0, high)
    assert 0.0 < flip(test, ref, mode) <= 1.0


def test_flip_mode_is_checked():
    x = np.zeros((8, 8, 3))
    with pytest.raises(ConfigError) as excinfo:
        flip(x, x, "sdr")
    one_line_error(excinfo, "metrics.flip.mode", "sdr")


def test_image_metrics_with_lpips_and_flip_from_the_real_config(random_model):
    cfg = compose_config().metrics
    assert cfg.lpips.enabled and cfg.flip.enabled and cfg.flip.mode == "hdr"
    rng = np.random.default_rng(7)
    reference = rng.uniform(0, 3, (24, 32, 3))
    denoised = np.clip(reference + rng.normal(0, 0.3, reference.shape), 0, None)
    m = image_metrics(denoised, reference, cfg)
    assert {"lpips", "flip"} <= set(m)
    assert m["lpips"] > 0 and 0 < m["flip"] <= 1
    assert m["flip"] == pytest.approx(flip(denoised, reference, "hdr"))
    x_ldr, y_ldr = tonemap(denoised, cfg.tonemap, cfg.gamma), tonemap(reference, cfg.tonemap, cfg.gamma)
    assert m["lpips"] == pytest.approx(lpips_distance(random_model, x_ldr, y_ldr), rel=1e-6)
    same = image_metrics(reference, reference, cfg)
    assert same["lpips"] == pytest.approx(0.0, abs=1e-6) and same["flip"] == pytest.approx(0.0, abs=1e-7)
    assert lpips_variant(cfg) == "vgg16-random(seed=0)+lin-uniform"
    ldr = compose_config(["metrics.flip.mode=ldr", "metrics.lpips.enabled=false"]).metrics
    m = image_metrics(denoised, reference, ldr)
    assert "lpips" not in m and lpips_variant(ldr) is None
    expected = flip(
        tonemap(denoised, ldr.tonemap, ldr.gamma), tonemap(reference, ldr.tonemap, ldr.gamma), "ldr"
    )
    assert m["flip"] == pytest.approx(expected)
