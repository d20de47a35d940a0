"""PNG output and comparison strips (src/io/images.py)."""

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from src.errors import DataError
from src.io.images import (
    RECT_RGB,
    SEPARATOR_PX,
    comparison_strip,
    crop_box,
    max_error_center,
    save_comparison_strip,
    to_uint8,
    write_png,
)
from tests.conftest import one_line_error


def three_panels(h=20, w=30, seed=0):
    rng = np.random.default_rng(seed)
    reference = rng.uniform(0.2, 0.8, (h, w, 3))
    noisy = np.clip(reference + rng.normal(0, 0.05, reference.shape), 0, 1)
    return [("noisy", noisy), ("denoised", (noisy + reference) / 2), ("reference", reference)]


@pytest.mark.parametrize(
    ("crop_size", "zoom", "crop_h", "col_w"),
    [(8, 3, 8, 30), (8, 5, 8, 40), (100, 2, 20, 60)],  # column = max(W, zoom * crop); crop <= image
)
def test_strip_shape(crop_size, zoom, crop_h, col_w):
    strip = comparison_strip(three_panels(), crop_size, zoom)
    assert strip.dtype == np.uint8
    assert strip.shape == (20 + SEPARATOR_PX + zoom * crop_h, 3 * col_w + 2 * SEPARATOR_PX, 3)


def test_strip_content_crop_and_rectangle():
    panels = three_panels()
    zoom, center = 3, (10, 12)
    strip = comparison_strip(panels, 8, zoom, crop_center=center)
    y0, x0, ch, cw = crop_box(center, 8, 20, 30)
    assert (y0, x0, ch, cw) == (6, 8, 8, 8)
    col = 30 + SEPARATOR_PX
    for i, (_, image) in enumerate(panels):
        full = to_uint8(image)
        left = i * col
        # Away from the outline the full image is unchanged.
        np.testing.assert_array_equal(strip[:5, left : left + 30], full[:5])
        assert tuple(strip[y0, left + x0]) == RECT_RGB  # outline corner
        # Bottom-right crop pixel (away from the label) is the zoomed source pixel.
        zoomed_br = strip[20 + SEPARATOR_PX + zoom * ch - 1, left + zoom * cw - 1]
        np.testing.assert_array_equal(zoomed_br, full[y0 + ch - 1, x0 + cw - 1])


def test_crop_center_finds_an_injected_error_block():
    rng = np.random.default_rng(3)
    reference = rng.uniform(0, 1, (40, 50, 3))
    noisy = reference + rng.normal(0, 0.02, reference.shape)
    noisy[10:18, 30:38] += 0.5  # the 8x8 region where noisy differs most from the reference
    assert max_error_center(noisy, reference, 8) == (14, 34)
    # The default crop of the strip is that block: its zoomed crop is the noisy block.
    strip = comparison_strip([("noisy", np.clip(noisy, 0, 1)), ("reference", reference)], 8, 6)
    crop = strip[40 + SEPARATOR_PX :, :48]
    expected = np.repeat(np.repeat(to_uint8(np.clip(noisy, 0, 1))[10:18, 30:38], 6, 0), 6, 1)
    np.testing.assert_array_equal(crop[-12:], expected[-12:])  # bottom rows, away from the label


def test_long_label_stays_in_its_column():
    image = np.zeros((10, 10, 3))
    long = comparison_strip([("a very long label for a tiny crop", image), ("b", image)], 4, 2, (5, 5))
    short = comparison_strip([("a", image), ("b", image)], 4, 2, (5, 5))
    # Column 0 spans x < 10: the separator and the second column do not see the first label.
    np.testing.assert_array_equal(long[:, 10:], short[:, 10:])
    assert (long[:, 10 : 10 + SEPARATOR_PX] == 255).all()


def test_crop_box_is_clamped_inside_the_image():
    assert crop_box((0, 0), 8, 20, 30) == (0, 0, 8, 8)
    assert crop_box((19, 29), 8, 20, 30) == (12, 22, 8, 8)
    assert crop_box((5, 5), 100, 20, 30) == (0, 0, 20, 30)
    assert max_error_center(np.ones((20, 30, 3)), np.zeros((20, 30, 3)), 100) == (10, 15)


def test_panels_of_different_shapes_are_rejected():
    with pytest.raises(DataError) as excinfo:
        comparison_strip([("a", np.zeros((4, 5, 3))), ("b", np.zeros((5, 4, 3)))], 2, 2)
    one_line_error(excinfo, "(4, 5, 3)", "(5, 4, 3)")


def test_png_round_trips_and_leaves_no_temporary_file(tmp_path):
    image = np.random.default_rng(4).uniform(-0.1, 1.1, (7, 11, 3))
    path = write_png(tmp_path / "sub" / "img.png", image)
    with Image.open(path) as png:
        assert png.mode == "RGB" and png.format == "PNG"
        np.testing.assert_array_equal(np.asarray(png), to_uint8(image))
    assert sorted(p.name for p in path.parent.iterdir()) == ["img.png"]


def test_failed_png_write_leaves_nothing(tmp_path, monkeypatch):
    def broken_save(self, fp, *args, **kwargs):
        Path(fp).write_bytes(b"\x89PNG partial")
        raise OSError("disk full")

    monkeypatch.setattr(Image.Image, "save", broken_save)
    with pytest.raises(OSError, match="disk full"):
        write_png(tmp_path / "img.png", np.zeros((4, 4, 3)))
    assert list(tmp_path.iterdir()) == []


def test_save_comparison_strip(tmp_path):
    panels = three_panels()
    path = save_comparison_strip(tmp_path / "strip.png", panels, 8, 3)
    with Image.open(path) as png:
        np.testing.assert_array_equal(np.asarray(png), comparison_strip(panels, 8, 3))


def test_a_temporal_strip_follows_one_crop_through_every_frame_of_every_row():
    from src.io.images import SEPARATOR_PX, temporal_strip

    rng = np.random.default_rng(0)
    reference = [rng.integers(0, 200, (20, 30, 3), dtype=np.uint8) for _ in range(3)]
    noisy = [r.copy() for r in reference]
    noisy[1][10:14, 20:24] = 255  # the middle frame differs most from the reference there
    denoised = [r // 2 for r in reference]
    strip = temporal_strip([("noisy", noisy), ("kpcn", denoised), ("reference", reference)], 4, 3)
    cell = 4 * 3
    assert strip.shape == (3 * cell + 2 * SEPARATOR_PX, 3 * cell + 2 * SEPARATOR_PX, 3)
    for r, frames in enumerate((noisy, denoised, reference)):
        for c, frame in enumerate(frames):
            if r == 0 or c == 0:
                continue  # labelled cells: text drawn on them
            top, left = r * (cell + SEPARATOR_PX), c * (cell + SEPARATOR_PX)
            want = np.repeat(np.repeat(frame[10:14, 20:24], 3, axis=0), 3, axis=1)  # the same window
            assert np.array_equal(strip[top : top + cell, left : left + cell], want), (r, c)
    with pytest.raises(DataError, match="same frames"):
        temporal_strip([("a", noisy), ("b", noisy[:2])], 4, 3)


def test_the_sequence_shown_is_the_first_with_two_frames_at_its_lowest_count():
    from src.report.figures import sequence_frames

    names = [
        "b-f0001-00004spp",
        "b-f0000-00004spp",
        "a-f0000-00008spp",  # one frame at 8 spp: not a sequence to follow
        "a-f0002-00016spp",
        "a-f0000-00016spp",
        "still-00004spp",
    ]
    assert sequence_frames(names) == ["a-f0000-00016spp", "a-f0002-00016spp"]
    assert sequence_frames(["still-00004spp", "lego-r_0"]) == []
