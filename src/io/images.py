"""LDR image output: PNG files and side-by-side comparison strips (noisy | denoised | reference).

Inputs are tone-mapped float images (H, W, 3) in [0, 1] (see `src.metrics.image.tonemap`); they are
quantised to 8 bits as round(255 * clip(x, 0, 1)). Files are written atomically (`src.io.atomic`).

Strip layout (one column per panel, columns separated by `SEPARATOR_PX` pixels of `SEPARATOR_RGB`):

    +-----------+--+-----------+--+-----------+
    | full  [ ] |  | full  [ ] |  | full  [ ] |   full images, crop region outlined
    +-----------+--+-----------+--+-----------+   separator row
    | label     |  | label     |  | label     |
    | crop x    |  | crop x    |  | crop x    |   crop zoomed by `zoom` (nearest neighbour)
    |   zoom    |  |   zoom    |  |   zoom    |
    +-----------+--+-----------+--+-----------+

A column is max(W, zoom * crop width) wide; a narrower image is left-aligned on the background.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from src.errors import DataError
from src.io.atomic import atomic_path

#: Gap between columns and between the full-image row and the crop row.
SEPARATOR_PX = 2
#: Background / separator colour.
SEPARATOR_RGB = (255, 255, 255)
#: Outline of the crop region on the full images.
RECT_RGB = (255, 0, 0)
RECT_WIDTH_PX = 1
#: Label text and the box behind it (so the label stays readable on any crop).
LABEL_RGB = (255, 255, 255)
LABEL_BOX_RGB = (0, 0, 0)
LABEL_MARGIN_PX = 2

Panel = tuple[str, np.ndarray]


def to_uint8(rgb01: np.ndarray) -> np.ndarray:
    """Float (H, W, 3) in [0, 1] -> uint8 as round(255 * clip(x, 0, 1)); uint8 input is returned as is."""
    rgb01 = np.asarray(rgb01)
    if rgb01.ndim != 3 or rgb01.shape[-1] != 3:
        raise DataError(f"expected an (H, W, 3) RGB image, got shape {rgb01.shape}")
    if rgb01.dtype == np.uint8:
        return rgb01
    if not np.isfinite(rgb01).all():
        raise DataError("image has NaN/Inf values; tone-map finite data before writing it")
    return np.round(np.clip(rgb01, 0.0, 1.0) * 255.0).astype(np.uint8)


def write_png(path: str | os.PathLike[str], rgb01: np.ndarray) -> Path:
    """Write an (H, W, 3) image (float in [0, 1], or uint8) as an 8-bit RGB PNG, atomically."""
    image = Image.fromarray(to_uint8(rgb01))
    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG")
    return Path(path)


def window_size(crop_size: int, height: int, width: int) -> tuple[int, int]:
    """(crop height, crop width): crop_size, but never larger than the image."""
    if crop_size < 1:
        raise DataError(f"crop_size must be >= 1, got {crop_size}")
    return min(crop_size, height), min(crop_size, width)


def max_error_center(first: np.ndarray, last: np.ndarray, crop_size: int) -> tuple[int, int]:
    """(row, col) centre of the crop_size window with the largest mean |first - last| (mean over
    channels and window pixels). Box sums come from a summed-area table, so this is O(H W); ties go
    to the top-most, then left-most window. The centre of a window at (y0, x0) of size (ch, cw) is
    (y0 + ch // 2, x0 + cw // 2), the inverse of `crop_box`."""
    err = np.abs(np.asarray(first, np.float64) - np.asarray(last, np.float64)).mean(axis=-1)
    h, w = err.shape
    ch, cw = window_size(crop_size, h, w)
    sat = np.zeros((h + 1, w + 1))
    sat[1:, 1:] = err.cumsum(axis=0).cumsum(axis=1)
    box = sat[ch:, cw:] - sat[:-ch, cw:] - sat[ch:, :-cw] + sat[:-ch, :-cw]
    y0, x0 = np.unravel_index(int(np.argmax(box)), box.shape)
    return int(y0) + ch // 2, int(x0) + cw // 2


def crop_box(center: tuple[int, int], crop_size: int, height: int, width: int) -> tuple[int, int, int, int]:
    """(y0, x0, ch, cw) of the crop window around `center`, shifted to lie inside the image."""
    ch, cw = window_size(crop_size, height, width)
    y0 = min(max(int(center[0]) - ch // 2, 0), height - ch)
    x0 = min(max(int(center[1]) - cw // 2, 0), width - cw)
    return y0, x0, ch, cw


def _check_panels(panels: Sequence[Panel]) -> list[tuple[str, np.ndarray]]:
    if not panels:
        raise DataError("comparison_strip: no panels")
    images = [(label, to_uint8(image)) for label, image in panels]
    shapes = {image.shape for _, image in images}
    if len(shapes) != 1:
        raise DataError(f"comparison_strip: panels differ in shape: {sorted(shapes)}")
    return images


def _draw_label(draw: ImageDraw.ImageDraw, label: str) -> None:
    """Label text at the top-left corner on a filled box, in Pillow's default font."""
    x = y = LABEL_MARGIN_PX
    left, top, right, bottom = draw.textbbox((x, y), label)
    m = LABEL_MARGIN_PX
    draw.rectangle((left - m, top - m, right + m, bottom + m), fill=LABEL_BOX_RGB)
    draw.text((x, y), label, fill=LABEL_RGB)


def comparison_strip(
    panels: Sequence[Panel], crop_size: int, zoom: int, crop_center: tuple[int, int] | None = None
) -> np.ndarray:
    """uint8 (H + SEPARATOR_PX + zoom * ch, n * col + (n - 1) * SEPARATOR_PX, 3) strip of `panels`.

    `panels` are (label, tone-mapped (H, W, 3) image in [0, 1]), all the same size, e.g. noisy |
    denoised | reference. `crop_center` (row, col) defaults to `max_error_center(panels[0], panels[-1])`:
    where the first panel (noisy) differs most from the last (reference). The crop window is clamped
    inside the image and shrunk to the image when crop_size is larger; col = max(W, zoom * cw).
    """
    if zoom < 1:
        raise DataError(f"comparison_strip: zoom must be >= 1, got {zoom}")
    images = _check_panels(panels)
    h, w, _ = images[0][1].shape
    if crop_center is None:
        crop_center = max_error_center(panels[0][1], panels[-1][1], crop_size)
    y0, x0, ch, cw = crop_box(crop_center, crop_size, h, w)
    col = max(w, zoom * cw)
    strip_h = h + SEPARATOR_PX + zoom * ch
    strip_w = len(images) * col + (len(images) - 1) * SEPARATOR_PX
    canvas = Image.new("RGB", (strip_w, strip_h), SEPARATOR_RGB)
    draw = ImageDraw.Draw(canvas)
    for i, (label, image) in enumerate(images):
        left = i * (col + SEPARATOR_PX)
        crop = image[y0 : y0 + ch, x0 : x0 + cw]
        zoomed = np.repeat(np.repeat(crop, zoom, axis=0), zoom, axis=1)  # nearest neighbour
        zoomed_image = Image.fromarray(np.ascontiguousarray(zoomed))
        # Drawn on the crop itself, so a label longer than the crop is clipped to its own column.
        _draw_label(ImageDraw.Draw(zoomed_image), label)
        canvas.paste(Image.fromarray(image), (left, 0))
        canvas.paste(zoomed_image, (left, h + SEPARATOR_PX))
        draw.rectangle(
            (left + x0, y0, left + x0 + cw - 1, y0 + ch - 1), outline=RECT_RGB, width=RECT_WIDTH_PX
        )
    return np.asarray(canvas, dtype=np.uint8).copy()


def temporal_strip(rows: Sequence[tuple[str, Sequence[np.ndarray]]], crop_size: int, zoom: int) -> np.ndarray:
    """uint8 strip of one crop through time: a row per `(label, frames)` (noisy, each method, reference;
    each row's frames the same sequence, all (H, W, 3) of one size), a column per frame, each cell the
    same crop_size window enlarged `zoom` times (nearest neighbour). The window is centred where the first
    row's middle frame differs most from the last row's (`max_error_center`): flicker there is what a
    temporal loss is meant to remove. The first cell of a row carries its label, the top row its frame."""
    if zoom < 1:
        raise DataError(f"temporal_strip: zoom must be >= 1, got {zoom}")
    frames = [[to_uint8(f) for f in row_frames] for _, row_frames in rows]
    counts = {len(f) for f in frames}
    shapes = {f.shape for row_frames in frames for f in row_frames}
    if not frames or len(counts) != 1 or not counts.pop() or len(shapes) != 1:
        raise DataError(f"temporal_strip: rows need the same frames of one size, got {sorted(shapes)}")
    h, w, _ = frames[0][0].shape
    middle = len(frames[0]) // 2
    y0, x0, ch, cw = crop_box(
        max_error_center(frames[0][middle], frames[-1][middle], crop_size), crop_size, h, w
    )
    cell_h, cell_w = zoom * ch, zoom * cw
    n_cols, n_rows = len(frames[0]), len(frames)
    canvas = Image.new(
        "RGB",
        (n_cols * cell_w + (n_cols - 1) * SEPARATOR_PX, n_rows * cell_h + (n_rows - 1) * SEPARATOR_PX),
        SEPARATOR_RGB,
    )
    for r, ((label, _), row_frames) in enumerate(zip(rows, frames, strict=True)):
        for c, frame in enumerate(row_frames):
            crop = frame[y0 : y0 + ch, x0 : x0 + cw]
            cell = Image.fromarray(
                np.ascontiguousarray(np.repeat(np.repeat(crop, zoom, axis=0), zoom, axis=1))
            )
            text = [label] if c == 0 else []
            text += [f"frame {c}"] if r == 0 else []
            if text:
                _draw_label(ImageDraw.Draw(cell), ", ".join(text))
            canvas.paste(cell, (c * (cell_w + SEPARATOR_PX), r * (cell_h + SEPARATOR_PX)))
    return np.asarray(canvas, dtype=np.uint8).copy()


def save_comparison_strip(
    path: str | os.PathLike[str],
    panels: Sequence[Panel],
    crop_size: int,
    zoom: int,
    crop_center: tuple[int, int] | None = None,
) -> Path:
    """`comparison_strip` written as a PNG at `path`, atomically; returns the path."""
    return write_png(path, comparison_strip(panels, crop_size, zoom, crop_center))
