"""LDR-FLIP (Andersson et al. 2020, "FLIP: A Difference Evaluator for Alternating Images", HPG) as the
Noisebase benchmark computes it: the PyTorch port in `noisebase/metrics/flip.py` (NVIDIA's reference code,
BSD-3-Clause, copyright 2020-2022 NVIDIA Corporation & Affiliates; code by Andersson, Nilsson and
Akenine-Moller), restricted to the LDR path its `flip(test, reference)` takes, on any device.

Why a port and not the package's function or `src.metrics.flip`: the package's code allocates its
tensors with `.cuda()` / `device='cuda'` throughout, so it cannot run without a GPU; NVIDIA's compiled
`flip_evaluator` (what `src.metrics.flip` calls) computes the same error map in another order and its
mean differs from the port's by up to ~2e-6 on 1080p frames, above the 1e-6 the protocol's parity test
holds. The operations below are the package's, in its order and precision (float32 tensors, float64
NumPy kernels cast to float32), so the numbers equal its numbers (tests/test_noisebase_metrics.py).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

#: Pixels per degree: 0.7 m from a 0.7 m wide, 3840-pixel display (the package's and FLIP's default).
PIXELS_PER_DEGREE = (0.7 * 3840 / 0.7) * np.pi / 180
QC, QF, PC, PT, EPS = 0.7, 0.5, 0.4, 0.95, 1e-15

_D65 = [[[0.950428545]], [[1.000000000]], [[1.088900371]]]
_INV_D65 = [[[1.052156925]], [[1.000000000]], [[0.918357670]]]
_LINRGB2XYZ = [
    [10135552 / 24577794, 8788810 / 24577794, 4435075 / 24577794],
    [2613072 / 12288897, 8788810 / 12288897, 887015 / 12288897],
    [1425312 / 73733382, 8788810 / 73733382, 70074185 / 73733382],
]
_XYZ2LINRGB = [
    [3.241003275, -1.537398934, -0.498615861],
    [-0.969224334, 1.875930071, 0.041554224],
    [0.055639423, -0.204011202, 1.057148933],
]


def flip(test: torch.Tensor, reference: torch.Tensor) -> float:
    """Mean LDR-FLIP error of (N, 3, H, W) sRGB-encoded frames in [0, 1] (the package's `flip`)."""
    return float(torch.mean(flip_map(test, reference)))


def flip_map(test: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """(N, 1, H, W) LDR-FLIP error map (`compute_ldrflip` on the frames in YCxCz)."""
    ref, out = _transform(reference, "srgb2ycxcz"), _transform(test, "srgb2ycxcz")
    device, ppd = reference.device, PIXELS_PER_DEGREE
    # Colour pipeline: CSF filtering, Hunt-adjusted L*a*b*, HyAB distance redistributed to [0, 1].
    filters = [_spatial_filter_kernel(ppd, c, device) for c in ("A", "RG", "BY")]
    radius = max(r for _, r in filters)
    kernels = [k for k, _ in filters]
    pre_ref = _hunt(_transform(_spatial_filter(ref, kernels, radius), "linrgb2lab"))
    pre_out = _hunt(_transform(_spatial_filter(out, kernels, radius), "linrgb2lab"))
    power_hyab = torch.pow(_hyab(pre_ref, pre_out, EPS), QC)
    green = _hunt(
        _transform(torch.tensor([[[0.0]], [[1.0]], [[0.0]]], device=device).unsqueeze(0), "linrgb2lab")
    )
    blue = _hunt(
        _transform(torch.tensor([[[0.0]], [[0.0]], [[1.0]]], device=device).unsqueeze(0), "linrgb2lab")
    )
    cmax = torch.pow(_hyab(green, blue, EPS), QC).item()
    pccmax = PC * cmax
    delta_c = torch.where(
        power_hyab < pccmax,
        (PT / pccmax) * power_hyab,
        PT + ((power_hyab - pccmax) / (cmax - pccmax)) * (1.0 - PT),
    )
    # Feature pipeline: edges and points of the normalised achromatic channel.
    ref_y, out_y = (ref[:, 0:1] + 16) / 116, (out[:, 0:1] + 16) / 116
    edges_ref, points_ref = _features(ref_y, ppd, "edge"), _features(ref_y, ppd, "point")
    edges_out, points_out = _features(out_y, ppd, "edge"), _features(out_y, ppd, "point")
    delta_f = torch.max(
        torch.abs(torch.norm(edges_ref, dim=1, keepdim=True) - torch.norm(edges_out, dim=1, keepdim=True)),
        torch.abs(torch.norm(points_out, dim=1, keepdim=True) - torch.norm(points_ref, dim=1, keepdim=True)),
    )
    delta_f = torch.pow((1 / np.sqrt(2)) * torch.clamp(delta_f, min=EPS), QF)
    return torch.pow(delta_c, 1 - delta_f)


def _spatial_filter_kernel(ppd: float, channel: str, device) -> tuple[torch.Tensor, int]:
    """The channel's contrast sensitivity kernel (`generate_spatial_filter`) and its radius."""
    params = {"A": (1, 0.0047, 0, 1e-5), "RG": (1, 0.0053, 0, 1e-5), "BY": (34.1, 0.04, 13.5, 0.025)}
    a1, b1, a2, b2 = params[channel]
    max_scale = max([0.0047, 1e-5, 0.0053, 1e-5, 0.04, 0.025])
    r = int(np.ceil(3 * np.sqrt(max_scale / (2 * np.pi**2)) * ppd))
    delta_x = 1.0 / ppd
    x, y = np.meshgrid(range(-r, r + 1), range(-r, r + 1))
    z = (x * delta_x) ** 2 + (y * delta_x) ** 2
    g = a1 * np.sqrt(np.pi / b1) * np.exp(-(np.pi**2) * z / b1) + a2 * np.sqrt(np.pi / b2) * np.exp(
        -(np.pi**2) * z / b2
    )
    g = g / np.sum(g)
    return torch.Tensor(g).unsqueeze(0).unsqueeze(0).to(device), r


def _spatial_filter(img: torch.Tensor, kernels: list[torch.Tensor], radius: int) -> torch.Tensor:
    """Each YCxCz channel convolved with its kernel (replicated borders), to linear RGB, clamped to [0, 1]."""
    pad = (radius, radius, radius, radius)
    channels = [
        nn.functional.conv2d(
            nn.functional.pad(img[:, c : c + 1], pad, mode="replicate"), kernels[c], padding=0
        )
        for c in range(3)
    ]
    return torch.clamp(_transform(torch.cat(channels, 1), "ycxcz2linrgb"), 0.0, 1.0)


def _hunt(img: torch.Tensor) -> torch.Tensor:
    """Hunt adjustment of L*a*b*: a and b scaled by 0.01 L."""
    lum = img[:, 0:1]
    return torch.cat((lum, torch.mul(0.01 * lum, img[:, 1:2]), torch.mul(0.01 * lum, img[:, 2:3])), 1)


def _hyab(reference: torch.Tensor, test: torch.Tensor, eps: float) -> torch.Tensor:
    delta = reference - test
    root = torch.sqrt(torch.clamp(torch.pow(delta[:, 0:1], 2), min=eps))
    return root + torch.norm(delta[:, 1:3], dim=1, keepdim=True)


def _features(img_y: torch.Tensor, ppd: float, kind: str) -> torch.Tensor:
    """Edge or point detector responses in x and y (`feature_detection`)."""
    w = 0.082
    sd = 0.5 * w * ppd
    radius = int(np.ceil(3 * sd))
    x, y = np.meshgrid(range(-radius, radius + 1), range(-radius, radius + 1))
    g = np.exp(-(x**2 + y**2) / (2 * sd * sd))
    gx = np.multiply(-x, g) if kind == "edge" else np.multiply(x**2 / (sd * sd) - 1, g)
    negative, positive = -np.sum(gx[gx < 0]), np.sum(gx[gx > 0])
    gx = torch.Tensor(gx)
    gx = torch.where(gx < 0, gx / negative, gx / positive).unsqueeze(0).unsqueeze(0).to(img_y.device)
    padded = nn.functional.pad(img_y, (radius, radius, radius, radius), mode="replicate")
    fx = nn.functional.conv2d(padded, gx, padding=0)
    fy = nn.functional.conv2d(padded, torch.transpose(gx, 2, 3), padding=0)
    return torch.cat((fx, fy), dim=1)


def _transform(color: torch.Tensor, what: str) -> torch.Tensor:
    """The colour-space transforms the LDR path uses (`color_space_transform`)."""
    device = color.device
    if what == "srgb2linrgb":
        return torch.where(
            color > 0.04045, torch.pow((torch.clamp(color, min=0.04045) + 0.055) / 1.055, 2.4), color / 12.92
        )
    if what in ("linrgb2xyz", "xyz2linrgb"):
        n, c, h, w = color.size()
        matrix = torch.Tensor(_LINRGB2XYZ if what == "linrgb2xyz" else _XYZ2LINRGB).to(device)
        return torch.matmul(matrix, color.reshape(n, c, h * w)).view(n, c, h, w)
    if what == "xyz2ycxcz":
        color = torch.mul(color, torch.tensor(_INV_D65, device=device))
        y = 116 * color[:, 1:2] - 16
        cx = 500 * (color[:, 0:1] - color[:, 1:2])
        cz = 200 * (color[:, 1:2] - color[:, 2:3])
        return torch.cat((y, cx, cz), 1)
    if what == "ycxcz2xyz":
        y = (color[:, 0:1] + 16) / 116
        cx, cz = color[:, 1:2] / 500, color[:, 2:3] / 200
        return torch.mul(torch.cat((y + cx, y, y - cz), 1), torch.tensor(_D65, device=device))
    if what == "xyz2lab":
        color = torch.mul(color, torch.tensor(_INV_D65, device=device))
        delta = 6 / 29
        delta_square = delta * delta
        delta_cube = delta * delta_square
        factor = 1 / (3 * delta_square)
        clamped = torch.pow(torch.clamp(color, min=delta_cube), 1.0 / 3.0).to(dtype=color.dtype)
        linear = (factor * color + (4 / 29)).to(dtype=color.dtype)
        color = torch.where(color > delta_cube, clamped, linear)
        lum = 116 * color[:, 1:2] - 16
        a = 500 * (color[:, 0:1] - color[:, 1:2])
        b = 200 * (color[:, 1:2] - color[:, 2:3])
        return torch.cat((lum, a, b), 1)
    steps = {
        "srgb2ycxcz": ("srgb2linrgb", "linrgb2xyz", "xyz2ycxcz"),
        "ycxcz2linrgb": ("ycxcz2xyz", "xyz2linrgb"),
        "linrgb2lab": ("linrgb2xyz", "xyz2lab"),
    }[what]
    for step in steps:
        color = _transform(color, step)
    return color
