"""The temporal loss (src/train/temporal.py) and the temporal-stability metric (src/metrics/temporal.py)."""

import numpy as np
import pytest
import torch

from src.errors import ConfigError, DataError
from src.metrics.temporal import temporal_error
from src.train.temporal import frame_differences, temporal_loss, warp_to_previous


def _static(n=2, k=3, c=3, h=5, w=7, seed=0):
    frame = torch.rand((n, 1, c, h, w), generator=torch.Generator().manual_seed(seed))
    return frame.expand(n, k, c, h, w).contiguous()


@pytest.mark.parametrize("mode", ["signed", "abs"])
def test_temporal_loss_is_zero_for_a_static_sequence_denoised_exactly(mode):
    reference = _static()
    assert temporal_loss(reference.clone(), reference, mode).item() == 0.0


def test_temporal_loss_is_positive_for_flicker_and_equals_its_closed_form():
    reference = _static()
    # Output = reference + alternating +-a per frame: every Δt is +-2a, the reference's 0.
    a = 0.05
    signs = torch.tensor([1.0, -1.0, 1.0]).view(1, 3, 1, 1, 1)
    flickering = reference + a * signs
    for mode in ("signed", "abs"):
        assert temporal_loss(flickering, reference, mode).item() == pytest.approx(2 * a, rel=1e-5)
    # A constant offset does not flicker: per-frame error, no temporal error.
    assert temporal_loss(reference + a, reference).item() == pytest.approx(0.0, abs=1e-7)


def test_abs_mode_ignores_the_sign_of_a_change():
    # The reference brightens by 0.1 per frame; an output that darkens by as much.
    ramp = torch.arange(3.0).view(1, 3, 1, 1, 1) * 0.1
    reference = _static() + ramp
    reversed_ = _static() - ramp
    assert temporal_loss(reversed_, reference, "signed").item() == pytest.approx(0.2, rel=1e-5)
    assert temporal_loss(reversed_, reference, "abs").item() == pytest.approx(0.0, abs=1e-6)


def test_warping_along_the_motion_removes_a_translation():
    # A pattern moving 2 pixels right per frame: frame t+1 sampled at x + 2 is frame t.
    g = torch.Generator().manual_seed(1)
    wide = torch.rand((1, 3, 6, 20), generator=g)
    frames = torch.stack([wide[..., 4 - 2 * t : 16 - 2 * t] for t in range(3)], dim=1)  # (1, 3, 3, 6, 12)
    motion = torch.zeros((1, 3, 2, 6, 12))
    motion[:, :, 0] = 2.0
    warped = frame_differences(frames, motion)
    assert warped[..., :, :-2].abs().max().item() < 1e-6  # away from the right border it clamps at
    assert frame_differences(frames).abs().mean().item() > 0.1  # unwarped, the motion is change
    # Zero motion is the identity.
    assert torch.allclose(warp_to_previous(frames[:, 1], torch.zeros((1, 2, 6, 12))), frames[:, 1], atol=1e-6)


def test_temporal_loss_rejects_bad_shapes_and_modes():
    with pytest.raises(ConfigError, match="temporal_mode"):
        temporal_loss(_static(), _static(), "squared")
    with pytest.raises(ValueError, match="k >= 2"):
        temporal_loss(_static(k=1), _static(k=1))


def test_temporal_error_metric_measures_flicker_in_display_units():
    rng = np.random.default_rng(0)
    reference = np.repeat(rng.uniform(0.1, 0.5, (1, 4, 6, 3)), 4, axis=0)  # static, within [0, 1]
    assert temporal_error(reference, reference) == 0.0
    # A static output off by a constant: no flicker (gamma 1 makes the closed form linear).
    assert temporal_error(reference * 0.9, reference, gamma=1.0) == pytest.approx(0.0, abs=1e-12)
    flicker = reference + 0.02 * np.array([1, -1, 1, -1]).reshape(4, 1, 1, 1)
    assert temporal_error(flicker, reference, gamma=1.0) == pytest.approx(0.04)
    with pytest.raises(DataError, match="temporal metric"):
        temporal_error(reference[:1], reference[:1])
