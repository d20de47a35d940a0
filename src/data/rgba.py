"""RGB(A) PNGs as float straight-alpha RGBA, and their exact box downscaling."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from src.errors import DataError


def read_rgba(path: Path) -> tuple[np.ndarray, bool]:
    """(H, W, 4) float32 in [0, 1] (straight alpha; alpha 1 when the file has none), and whether the file
    has an alpha channel."""
    try:
        with Image.open(path) as img:
            img.load()
            if img.mode == "P":  # palette: lossless expansion, keeping a transparency entry if any
                img = img.convert("RGBA" if "transparency" in img.info else "RGB")
            if img.mode not in ("RGB", "RGBA"):
                raise DataError(
                    f"{path}: image has {len(img.getbands())} channel(s) (PIL mode {img.mode}); expected 3 "
                    "(RGB) or 4 (RGBA)"
                )
            pixels = np.asarray(img)
    except (OSError, Image.DecompressionBombError) as err:
        raise DataError(f"{path}: unreadable image ({err}); expected an RGB(A) PNG") from err
    if pixels.dtype != np.uint8:
        raise DataError(f"{path}: image samples are {pixels.dtype}; expected 8-bit")
    rgba = pixels.astype(np.float32) / 255.0
    has_alpha = rgba.shape[-1] == 4
    if not has_alpha:
        rgba = np.concatenate([rgba, np.ones_like(rgba[..., :1])], axis=-1)
    return rgba, has_alpha


def downscale_rgba(rgba: np.ndarray, factor: int) -> np.ndarray:
    """Area-average (H, W, 4) straight-alpha RGBA by an integer ``factor`` (H, W divisible by it).

    Averages *premultiplied* colour (rgb * alpha) and alpha over each factor x factor block, then
    returns straight colour (0 where the block is fully transparent). Averaging straight colour instead
    lets the arbitrary colour stored in transparent pixels (often black) bleed into object edges as a
    dark halo. A numpy reshape-mean in float32 is used rather than PIL's resize: it is exactly the box
    average over the block (the pixel footprint that mip-NeRF's multiscale data assumes), with no
    requantisation to 8 bits in between and no dependence on the PIL version's alpha handling.
    """
    if factor == 1:
        return rgba
    h, w, c = rgba.shape
    premul = np.concatenate([rgba[..., :3] * rgba[..., 3:], rgba[..., 3:]], axis=-1)
    blocks = premul.reshape(h // factor, factor, w // factor, factor, c).mean(axis=(1, 3))
    alpha = blocks[..., 3:]
    rgb = np.divide(blocks[..., :3], alpha, out=np.zeros_like(blocks[..., :3]), where=alpha > 0)
    return np.concatenate([rgb, alpha], axis=-1).astype(np.float32)
