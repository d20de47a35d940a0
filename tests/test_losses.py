"""Training losses (src/objectives/losses.py) by value against numpy, on signed and unequal tensors."""

import numpy as np
import pytest
import torch

from src.errors import ConfigError
from src.objectives import losses
from src.objectives.losses import LOSSES, get_loss, l1, l2, relmse, smape
from tests.conftest import one_line_error


def _pair(seed=0, shape=(2, 3, 4, 5)):
    """A prediction and a target with negative values, zeros and values far above 1."""
    rng = np.random.default_rng(seed)
    pred, target = rng.normal(0.0, 2.0, shape), rng.normal(0.5, 3.0, shape)
    pred.flat[0], target.flat[1] = 0.0, 0.0
    pred.flat[2] = target.flat[2] = 0.0  # a black pixel: 0 / eps
    return pred, target


def _t(*arrays):
    return [torch.from_numpy(a) for a in arrays]


def test_smape_of_negative_values_keeps_its_denominator_positive():
    # One channel each: |p - t| / (|p| + |t| + eps). Without the absolute values in the denominator a
    # prediction of -1 against a target of 1 divides 2 by 0.01 (200 instead of 0.995).
    pred, target = torch.tensor([-1.0, -2.0, 3.0, 0.0]), torch.tensor([1.0, -0.5, 1.0, 0.0])
    per_element = [2 / 2.01, 1.5 / 2.51, 2 / 4.01, 0.0]
    assert smape(pred, target).item() == pytest.approx(np.mean(per_element), rel=1e-6)
    assert smape(pred, target, eps=0.5).item() == pytest.approx(
        np.mean([2 / 2.5, 1.5 / 3, 2 / 4.5, 0]), rel=1e-6
    )
    assert smape(torch.tensor([-1.0]), torch.tensor([1.0])).item() == pytest.approx(2 / 2.01, rel=1e-6)


def test_each_loss_equals_its_closed_form_on_signed_values():
    pred, target = _pair()
    p, t = _t(pred, target)
    eps = 0.01
    expected = {
        "l1": np.abs(pred - target).mean(),
        "l2": ((pred - target) ** 2).mean(),
        "smape": (np.abs(pred - target) / (np.abs(pred) + np.abs(target) + eps)).mean(),
        "relmse": ((pred - target) ** 2 / (target**2 + eps)).mean(),
    }
    for name, value in expected.items():
        assert LOSSES[name](p, t).item() == pytest.approx(value, rel=1e-12), name
    # relMSE and SMAPE are not symmetric in the same way: swapping the arguments changes relMSE only.
    assert smape(t, p).item() == pytest.approx(expected["smape"], rel=1e-12)
    assert relmse(t, p).item() != pytest.approx(expected["relmse"], rel=1e-3)


@pytest.mark.parametrize("eps", [0.3, 2.0])
def test_the_eps_of_smape_and_relmse_is_the_one_given(eps):
    pred, target = _pair(seed=1)
    p, t = _t(pred, target)
    smape_value = (np.abs(pred - target) / (np.abs(pred) + np.abs(target) + eps)).mean()
    relmse_value = ((pred - target) ** 2 / (target**2 + eps)).mean()
    assert smape(p, t, eps).item() == pytest.approx(smape_value, rel=1e-12)
    assert relmse(p, t, eps).item() == pytest.approx(relmse_value, rel=1e-12)


def test_the_default_eps_is_0_01():
    # On a black target pixel the eps is the whole denominator: 1 / (0 + 0 + eps) and 1 / (0 + eps).
    pred, target = torch.tensor([0.5, -2.0]), torch.tensor([0.0, 0.0])
    assert smape(pred, target).item() == pytest.approx((0.5 / 0.51 + 2.0 / 2.01) / 2, rel=1e-6)
    assert relmse(pred, target).item() == pytest.approx((0.25 / 0.01 + 4.0 / 0.01) / 2, rel=1e-6)
    zero = torch.zeros(3)
    assert smape(zero, zero).item() == 0.0 and relmse(zero, zero).item() == 0.0


def test_gradients_reach_the_prediction_and_only_relmse_holds_its_target_constant():
    pred, target = _pair(seed=2, shape=(6,))
    for name in ("l1", "l2", "smape", "relmse"):
        p, t = (torch.from_numpy(a).requires_grad_() for a in (pred, target))
        LOSSES[name](p, t).backward()
        assert p.grad is not None and p.grad.abs().sum() > 0, name
        if name == "relmse":
            assert t.grad is None  # detached: no gradient flows into the target
        else:
            assert t.grad is not None and t.grad.abs().sum() > 0, name
    # relMSE's gradient with respect to the prediction: 2 (p - t) / (t^2 + eps) / n.
    p = torch.from_numpy(pred).requires_grad_()
    relmse(p, torch.from_numpy(target)).backward()
    np.testing.assert_allclose(p.grad.numpy(), 2 * (pred - target) / (target**2 + 0.01) / 6, rtol=1e-12)


def test_get_loss_by_name_and_by_target_with_bound_options():
    assert {"l1": l1, "l2": l2, "smape": smape, "relmse": relmse} == LOSSES
    for name, fn in LOSSES.items():
        assert get_loss(name) is fn
    pred, target = _t(*_pair(seed=3))
    bound = get_loss({"_target_": "src.objectives.losses.smape", "eps": 0.5})
    expected = (np.abs(pred.numpy() - target.numpy()) / (pred.abs() + target.abs() + 0.5).numpy()).mean()
    assert bound(pred, target).item() == pytest.approx(expected, rel=1e-12)
    assert get_loss({"_target_": "src.objectives.losses.relmse"}) is losses.relmse  # no options: the function


def test_get_loss_errors_are_one_line_naming_the_setting():
    with pytest.raises(ConfigError) as err:
        get_loss("l3")
    one_line_error(err, "task.train.loss='l3'", "['l1', 'l2', 'relmse', 'smape']", "_target_")
    with pytest.raises(ConfigError) as err:
        get_loss({"_target_": "src.objectives.losses.nope"})
    one_line_error(err, "task.train.loss._target_", "nope")
