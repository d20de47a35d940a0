"""The `denoise` report: the per-model table and the KPCN/DPCN and kernel-application ratios."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from src.bench.denoise_timing import Row
from src.bench.table import format_line


def _fmt(x: float | None, spec: str) -> str:
    return "n/a" if x is None else format(x, spec)


def format_table(rows: Sequence[Row], pixels: int, baseline: Row) -> str:
    """Fixed-width table: per frame, per megapixel, FLOPs, throughput and its share of the conv2d rate."""
    base_rate = baseline.flops_per_pixel * pixels / baseline.seconds
    header = ("model", "params", "GFLOP/frame", "s/frame", "s/MPix", "GFLOP/s", "% conv2d", "note")
    lines = [header]
    for r in rows:
        gflop = None if r.flops_per_pixel is None else r.flops_per_pixel * pixels / 1e9
        rate = None if gflop is None or r.seconds is None else gflop / r.seconds
        lines.append(
            (
                r.name,
                "-" if r.params is None else f"{r.params:,}",
                _fmt(gflop, ",.2f"),
                _fmt(r.seconds, ".4f"),
                _fmt(None if r.seconds is None else r.seconds / (pixels / 1e6), ".4f"),
                _fmt(rate, ",.1f"),
                _fmt(None if rate is None else 100 * rate * 1e9 / base_rate, ".0f"),
                r.note,
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join(format_line(line, widths) for line in lines)


def _ratio(a: Row | None, b: Row | None, attr: str) -> str:
    x, y = (getattr(a, attr, None), getattr(b, attr, None)) if a and b else (None, None)
    return "n/a" if not x or not y else f"{x / y:.2f}x"


def format_ratios(by_name: Mapping[str, Row]) -> list[str]:
    kpcn, dpcn = by_name.get("kpcn"), by_name.get("dpcn")
    lines = [
        "ratios:",
        f"  KPCN / DPCN time:  {_ratio(kpcn, dpcn, 'seconds')}   "
        f"(FLOP ratio KPCN / DPCN: {_ratio(kpcn, dpcn, 'flops_per_pixel')}, "
        "from the 441-channel kernel output layer vs 3 channels)",
    ]
    for name, row in by_name.items():
        net = by_name.get(f"{name} (net only)")
        if net is not None:
            lines.append(
                f"  kernel-application overhead, {name} total / {name} net only (equal backbone): "
                f"{_ratio(row, net, 'seconds')}   "
                f"(target <= ~1.2x; FLOP ratio {_ratio(row, net, 'flops_per_pixel')})"
            )
    unet, oidn = by_name.get("unet_kpcn"), by_name.get("oidn")
    if unet is not None:
        lines += [
            f"  unet_kpcn / kpcn time: {_ratio(unet, kpcn, 'seconds')}   "
            f"(FLOP ratio {_ratio(unet, kpcn, 'flops_per_pixel')}; target <= 0.10x: >= 10x faster)",
            f"  unet_kpcn / oidn time: {_ratio(unet, oidn, 'seconds')}   (target <= 2x)",
        ]
    return lines
