"""The two forms of the sRGB curve (src/io/srgb.py) are the same curve, each checked against the standard."""

import numpy as np
import torch

from src.io.srgb import linear_to_srgb, srgb_oetf


def test_both_forms_follow_the_standard_and_agree():
    x = np.linspace(0.0, 1.0, 10001)
    standard = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(srgb_oetf(x), standard, rtol=0, atol=1e-15)
    torch_form = linear_to_srgb(torch.from_numpy(x)).numpy()
    np.testing.assert_allclose(torch_form, standard, rtol=0, atol=1e-12)
    assert srgb_oetf(0.0) == 0.0 and abs(srgb_oetf(1.0) - 1.0) < 1e-15


def test_the_torch_form_has_a_finite_gradient_at_zero():
    x = torch.tensor([0.0, 1e-3, 0.5], dtype=torch.float32, requires_grad=True)
    linear_to_srgb(x).sum().backward()
    assert torch.isfinite(x.grad).all() and x.grad[0] == np.float32(12.92)
