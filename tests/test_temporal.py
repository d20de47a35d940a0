"""The temporal loss (src/objectives/temporal.py) and the temporal-stability metric
(src/metrics/temporal.py)."""

import numpy as np
import pytest
import torch

from src.errors import ConfigError, DataError
from src.metrics.temporal import temporal_error
from src.objectives.temporal import frame_differences, temporal_loss, warp_to_previous


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


# -- by value, against per-pair loops in numpy: a moving reference, unequal changes, time-varying motion --


def _np_warp(next_frame, motion):
    """Frame t+1 read at (y + m_y, x + m_x), integer motion, the coordinates clamped to the image:
    (C, H, W), (2, H, W) -> (C, H, W)."""
    _, h, w = next_frame.shape
    ys, xs = np.mgrid[:h, :w]
    yy = np.clip(ys + motion[1].astype(int), 0, h - 1)
    xx = np.clip(xs + motion[0].astype(int), 0, w - 1)
    return next_frame[:, yy, xx]


def _np_temporal_loss(output, reference, mode="signed", motion=None):
    """The temporal loss by explicit loops over samples and consecutive frame pairs (t, t+1), frame t+1
    warped with frame t's motion."""
    n, k = output.shape[:2]
    terms = []
    for i in range(n):
        for t in range(k - 1):
            pair = []
            for x in (output, reference):
                following = x[i, t + 1] if motion is None else _np_warp(x[i, t + 1], motion[i, t])
                pair.append(following - x[i, t])
            d_out, d_ref = pair
            if mode == "abs":
                d_out, d_ref = np.abs(d_out), np.abs(d_ref)
            terms.append(np.abs(d_out - d_ref))
    return float(np.mean(terms))


def _moving(n=2, k=4, c=3, h=5, w=6, seed=0):
    """A reference whose every frame differs (signed values), and an output whose error changes unequally
    from frame to frame (unlike the flicker of +-a above)."""
    rng = np.random.default_rng(seed)
    reference = rng.normal(0.0, 1.0, (n, k, c, h, w))
    output = reference + rng.normal(0.0, 0.3, (n, k, c, h, w)) * rng.uniform(0.2, 2.0, (n, k, 1, 1, 1))
    return output, reference


def _integer_motion(n=2, k=4, h=5, w=6, seed=1):
    """Per-pixel integer motion in [-2, 2], different for every sample and frame (so that using another
    frame's motion, or another sample's, changes the answer); some of it points past the border."""
    return np.random.default_rng(seed).integers(-2, 3, (n, k, 2, h, w)).astype(np.float32)


@pytest.mark.parametrize("mode", ["signed", "abs"])
def test_temporal_loss_of_a_moving_sequence_equals_the_per_pair_loop(mode):
    output, reference = _moving()
    expected = _np_temporal_loss(output, reference, mode)
    got = temporal_loss(torch.from_numpy(output), torch.from_numpy(reference), mode).item()
    assert got == pytest.approx(expected, rel=1e-12)
    # The two modes differ on this fixture (the signs of the changes matter), and both are far from 0.
    assert _np_temporal_loss(output, reference, "signed") > _np_temporal_loss(output, reference, "abs") > 0.05


@pytest.mark.parametrize("mode", ["signed", "abs"])
def test_warped_temporal_loss_with_time_varying_motion_equals_the_per_pair_loop(mode):
    output, reference = (x.astype(np.float32) for x in _moving(seed=2))
    motion = _integer_motion()
    expected = _np_temporal_loss(output, reference, mode, motion)
    out_t, ref_t, motion_t = map(torch.from_numpy, (output, reference, motion))
    got = temporal_loss(out_t, ref_t, mode, motion_t).item()
    assert got == pytest.approx(expected, rel=1e-5)
    # The motion matters: the unwarped loss, and the loss warped with each frame's successor's motion, differ.
    assert _np_temporal_loss(output, reference, mode) != pytest.approx(expected, rel=1e-3)
    shifted = np.concatenate([motion[:, 1:], motion[:, :1]], axis=1)
    assert _np_temporal_loss(output, reference, mode, shifted) != pytest.approx(expected, rel=1e-3)


def test_frame_differences_warp_each_sample_with_its_own_motion_of_frame_t():
    frames = torch.from_numpy(_moving(seed=3)[1].astype(np.float32))
    motion = _integer_motion(seed=4)
    got = frame_differences(frames, torch.from_numpy(motion).double())  # float64 motion, float32 frames
    assert got.shape == (2, 3, 3, 5, 6) and got.dtype == torch.float32
    f = frames.numpy()
    for i in range(2):
        for t in range(3):
            expected = _np_warp(f[i, t + 1], motion[i, t]) - f[i, t]
            np.testing.assert_allclose(got[i, t].numpy(), expected, atol=1e-5, err_msg=f"sample {i} pair {t}")
    unwarped = frame_differences(frames)
    torch.testing.assert_close(unwarped, frames[:, 1:] - frames[:, :-1], rtol=0, atol=0)


def test_warp_reads_down_and_right_and_clamps_at_the_border():
    # A 3 x 4 ramp, value 10 y + x: reading at (y + m_y, x + m_x) is the ramp shifted, clamped at the edges.
    h, w = 3, 4
    ramp = (10.0 * torch.arange(h).view(h, 1) + torch.arange(w).view(1, w)).expand(1, 1, h, w)
    for m_x, m_y in [(0.0, 1.0), (0.0, -1.0), (2.0, 0.0), (-3.0, 2.0), (1.0, 5.0)]:
        motion = torch.tensor([m_x, m_y]).view(1, 2, 1, 1).expand(1, 2, h, w)
        ys = np.clip(np.arange(h) + int(m_y), 0, h - 1)
        xs = np.clip(np.arange(w) + int(m_x), 0, w - 1)
        expected = 10.0 * ys[:, None] + xs[None, :]
        got = warp_to_previous(ramp, motion)[0, 0].numpy()
        np.testing.assert_allclose(got, expected, atol=1e-5, err_msg=f"motion ({m_x}, {m_y})")
    # Half a pixel: bilinear, the mean of the two neighbours.
    half = torch.tensor([0.5, 0.0]).view(1, 2, 1, 1).expand(1, 2, h, w)
    np.testing.assert_allclose(warp_to_previous(ramp, half)[0, 0, 0, :3].numpy(), [0.5, 1.5, 2.5], atol=1e-5)


@pytest.mark.parametrize(("h", "w"), [(2, 2), (1, 3), (3, 1)])
def test_warp_is_exact_on_images_two_or_one_pixels_across(h, w):
    # The normalisation divides by (size - 1), or by 1 for a single pixel.
    image = torch.arange(1.0, 1.0 + h * w).view(1, 1, h, w)
    motion = torch.ones((1, 2, h, w))  # one pixel right and down
    ys, xs = np.minimum(np.arange(h) + 1, h - 1), np.minimum(np.arange(w) + 1, w - 1)
    expected = image[0, 0].numpy()[ys][:, xs]
    np.testing.assert_allclose(warp_to_previous(image, motion)[0, 0].numpy(), expected, atol=1e-6)


def test_warp_builds_its_sampling_grid_on_the_device_of_the_frames():
    # On the meta device (no data, devices checked as on a GPU): a grid made on the CPU would not mix.
    frames = torch.zeros((2, 3, 4, 5), device="meta")
    warped = warp_to_previous(frames, torch.zeros((2, 2, 4, 5), device="meta"))
    assert warped.device.type == "meta" and warped.shape == (2, 3, 4, 5)


@pytest.mark.parametrize("mode", ["signed", "abs"])
def test_temporal_loss_of_two_frames_is_the_one_pair(mode):
    output, reference = _moving(k=2, seed=5)
    got = temporal_loss(torch.from_numpy(output), torch.from_numpy(reference), mode).item()
    d_out, d_ref = output[:, 1] - output[:, 0], reference[:, 1] - reference[:, 0]
    if mode == "abs":
        d_out, d_ref = np.abs(d_out), np.abs(d_ref)
    assert got == pytest.approx(np.abs(d_out - d_ref).mean(), rel=1e-12)


def test_temporal_loss_rejects_sequences_of_different_shapes_even_when_they_broadcast():
    output = torch.zeros((1, 3, 3, 4, 5))
    for reference in (torch.zeros((1, 3, 3, 4, 1)), torch.zeros((1, 3, 3, 4, 6)), torch.zeros((3, 3, 4, 5))):
        with pytest.raises(ValueError, match="one shape"):
            temporal_loss(output, reference)


def _np_tonemap(x, method, gamma):
    x = np.asarray(x, dtype=np.float64)
    if method == "clip_gamma":
        return np.minimum(np.maximum(x, 0.0), 1.0) ** (1.0 / gamma)
    positive = np.maximum(x, 0.0)
    return (positive / (1.0 + positive)) ** (1.0 / gamma)


def _np_temporal_error(frames, reference, method="clip_gamma", gamma=2.2):
    """mean over consecutive pairs (t, t+1), pixels and channels of |Δ tm(frames) - Δ tm(reference)|."""
    per_pair = []
    for t in range(frames.shape[0] - 1):
        d_out = _np_tonemap(frames[t + 1], method, gamma) - _np_tonemap(frames[t], method, gamma)
        d_ref = _np_tonemap(reference[t + 1], method, gamma) - _np_tonemap(reference[t], method, gamma)
        per_pair.append(np.abs(d_out - d_ref).mean())
    return float(np.mean(per_pair))


def _moving_hdr(f=4, h=3, w=5, seed=6):
    """A moving HDR reference (values below 0 and above 1, so that the tone map's clip matters) and an
    output whose error differs from frame to frame."""
    rng = np.random.default_rng(seed)
    reference = rng.uniform(-0.2, 1.5, (f, h, w, 3))
    output = reference + rng.normal(0.0, 0.2, (f, h, w, 3)) * rng.uniform(0.2, 2.0, (f, 1, 1, 1))
    return output, reference


TONEMAPS = [("clip_gamma", 2.2), ("clip_gamma", 1.0), ("reinhard_gamma", 2.2), ("reinhard_gamma", 3.0)]


@pytest.mark.parametrize(("method", "gamma"), TONEMAPS)
def test_temporal_error_of_a_moving_sequence_equals_the_per_pair_loop(method, gamma):
    output, reference = _moving_hdr()
    expected = _np_temporal_error(output, reference, method, gamma)
    assert temporal_error(output, reference, method, gamma) == pytest.approx(expected, rel=1e-12)
    assert expected > 0.05


def test_temporal_error_defaults_to_clip_and_gamma_2_2():
    output, reference = _moving_hdr(seed=7)
    expected = _np_temporal_error(output, reference)  # clip_gamma, 2.2
    assert temporal_error(output, reference) == pytest.approx(expected, rel=1e-12)


def test_temporal_error_of_an_output_that_moves_as_the_reference_is_zero_only_then():
    # A moving reference in [0, 1]; gamma 1 makes the tone map linear there: a constant offset cancels,
    # a frozen output (the first frame repeated) scores the reference's own mean |Δt|.
    rng = np.random.default_rng(8)
    reference = rng.uniform(0.2, 0.7, (5, 2, 3, 3))
    assert temporal_error(reference + 0.1, reference, gamma=1.0) == pytest.approx(0.0, abs=1e-12)
    frozen = np.repeat(reference[:1], 5, axis=0)
    moving = np.mean([np.abs(reference[t + 1] - reference[t]).mean() for t in range(4)])
    assert temporal_error(frozen, reference, gamma=1.0) == pytest.approx(moving, rel=1e-12)


def test_temporal_error_of_two_frames_and_its_shape_checks():
    output, reference = _moving_hdr(f=2, seed=9)
    expected = _np_temporal_error(output, reference)  # clip_gamma, 2.2
    assert temporal_error(output, reference) == pytest.approx(expected, rel=1e-12)
    for bad in (reference[..., :1], reference[:, :, :1], reference[None]):  # broadcastable or 5-d
        with pytest.raises(DataError, match="temporal metric"):
            temporal_error(output if bad.ndim == 4 else output[None], bad)


# Surviving mutants of src/objectives/temporal.py (bash scripts/mutation.sh temporal), all equivalent here:
# - warp_to_previous `torch.meshgrid(..., indexing="ij")` -> `indexing=None` / dropped (2 mutants): "ij" is
#   torch.meshgrid's default; without the argument torch warns once per process, so no test can see it
#   reliably.
# - warp_to_previous `F.grid_sample(..., mode="bilinear", ...)` -> no mode: "bilinear" is the default.
