"""The machine's achievable convolution throughput: a plain `F.conv2d` (100 -> 100 channels, 5x5, the
DPCN hidden layer) over the same frame, in the same tiles, that the denoisers' GFLOP/s are compared to."""

from __future__ import annotations

import torch
import torch.nn.functional as F

from src.bench.denoise_timing import Prepared, Row, frame_tiles

#: The reference convolution: the DPCN/KPCN hidden layer of Bako et al. 2017 (100 -> 100 channels, 5x5).
BASELINE_CONV = {"channels": 100, "kernel": 5}


def conv_baseline(height: int, width: int, tile: int, device: torch.device) -> Prepared:
    """F.conv2d 100 -> 100, 5x5, 'same' padding over the frame in the same tiles (no halo): its row and
    the function that runs it once."""
    c, k = BASELINE_CONV["channels"], BASELINE_CONV["kernel"]
    x = torch.randn(1, c, height, width, device=device)
    weight = torch.randn(c, c, k, k, device=device) / (c * k * k) ** 0.5
    bias = torch.zeros(c, device=device)

    def run() -> None:
        for ys in frame_tiles(height, tile):
            for xs in frame_tiles(width, tile):
                F.conv2d(x[..., ys, xs], weight, bias, padding=k // 2)

    name = f"conv2d {c}->{c} {k}x{k}"
    flops = 2.0 * c * c * k * k
    return Row(name, None, flops_per_pixel=flops, note="plain F.conv2d, reference", key="conv2d"), run
