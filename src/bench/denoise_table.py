"""The `denoise` report: the per-model table, each model's spread over the rounds, the KPCN/DPCN and
kernel-application ratios, and the U-Net KPCN's claims as per-round time ratios."""

from __future__ import annotations

from collections.abc import Mapping, Sequence

from src.bench.denoise_timing import Row
from src.bench.table import format_line
from src.bench.timing import Rounds, Spread, ratio_spread

#: The U-Net KPCN's speed claims (Zhu et al. 2023, "Denoising Production Volumetric Rendering"): its time
#: over each reference's, at most this. The talk compares with "KPCN" without saying which form, so both
#: are printed: `kpcn` (Bako et al. 2017's two-branch KPCN of still images) and `kpcn_frame` (the
#: one-branch KPCN that the `unet_vs_kpcn` study trains per frame on the sequences' radiance).
CLAIMS = (
    ("kpcn", 0.10, "two-branch still-image KPCN (Bako et al. 2017)"),
    ("kpcn_frame", 0.10, "one-branch KPCN the unet_vs_kpcn study trains per frame"),
    ("oidn", 2.0, "Intel Open Image Denoise"),
)


def _fmt(x: float | None, spec: str) -> str:
    return "n/a" if x is None else format(x, spec)


def _lines(header: Sequence[str], cells: Sequence[Sequence[str]]) -> str:
    widths = [max(len(line[i]) for line in [header, *cells]) for i in range(len(header))]
    return "\n".join(format_line(line, widths) for line in [header, *cells])


def format_table(rows: Sequence[Row], pixels: int, baseline: Row) -> str:
    """Fixed-width table: conv depth, per frame (the median over the rounds), per megapixel, FLOPs,
    throughput and its share of the conv2d rate."""
    base_rate = baseline.flops_per_pixel * pixels / baseline.seconds
    header = (
        "model",
        "params",
        "conv layers",
        "GFLOP/frame",
        "s/frame",
        "s/MPix",
        "GFLOP/s",
        "% conv2d",
        "note",
    )
    cells = []
    for r in rows:
        gflop = None if r.flops_per_pixel is None else r.flops_per_pixel * pixels / 1e9
        rate = None if gflop is None or r.seconds is None else gflop / r.seconds
        cells.append(
            (
                r.name,
                "-" if r.params is None else f"{r.params:,}",
                "-" if r.depth is None else str(r.depth),
                _fmt(gflop, ",.2f"),
                _fmt(r.seconds, ".4f"),
                _fmt(None if r.seconds is None else r.seconds / (pixels / 1e6), ".4f"),
                _fmt(rate, ",.1f"),
                _fmt(None if rate is None else 100 * rate * 1e9 / base_rate, ".0f"),
                r.note,
            )
        )
    return _lines(header, cells)


def format_spreads(rows: Sequence[Row], rounds: int, warmup: int) -> str:
    """Per timed row: the median, interquartile range and range of its seconds per frame over the rounds."""
    title = (
        f"seconds per frame over {rounds} rounds (after {warmup} warm-up; a round times every row once, "
        "in an order that rotates between rounds):"
    )
    header = ("  model", "median", "IQR", "min - max", "(max - min) / median")
    cells = [
        (
            f"  {r.name}",
            f"{s.median:.4f}",
            f"{s.q1:.4f} - {s.q3:.4f}",
            f"{s.low:.4f} - {s.high:.4f}",
            f"{100 * (s.high - s.low) / s.median:.0f}%" if s.median else "n/a",
        )
        for r in rows
        if (s := r.spread) is not None
    ]
    return title + "\n" + _lines(header, cells)


def per_round_ratio(rounds: Rounds, a: Row | None, b: Row | None) -> tuple[Spread, list[float]] | None:
    """a's time over b's in each round (both timed in it, under the same load), or None if either did
    not run."""
    if a is None or b is None or a.key not in rounds.seconds or b.key not in rounds.seconds:
        return None
    return ratio_spread(rounds.seconds[a.key], rounds.seconds[b.key])


def _ratio_text(ratio: tuple[Spread, list[float]] | None) -> str:
    if ratio is None:
        return "n/a"
    s = ratio[0]
    return f"{s.median:.3g}x [{s.low:.3g} - {s.high:.3g}]"


def _flop_ratio(a: Row | None, b: Row | None) -> str:
    x, y = (a.flops_per_pixel, b.flops_per_pixel) if a and b else (None, None)
    return "n/a" if not x or not y else f"{x / y:.2f}x"


def format_ratios(by_key: Mapping[str, Row], rounds: Rounds) -> list[str]:
    """The KPCN/DPCN time ratio and each kernel model's kernel-application overhead, per round: median
    [min - max]."""
    kpcn, dpcn = by_key.get("kpcn"), by_key.get("dpcn")
    lines = [
        "ratios (per round: median [min - max] over the rounds):",
        f"  KPCN / DPCN time:  {_ratio_text(per_round_ratio(rounds, kpcn, dpcn))}   "
        f"(FLOP ratio KPCN / DPCN: {_flop_ratio(kpcn, dpcn)}, "
        "from the 441-channel kernel output layer vs 3 channels)",
    ]
    for key, row in by_key.items():
        net = by_key.get(f"{key}_net_only")
        if net is not None:
            lines.append(
                f"  kernel-application overhead, {key} total / {key} net only (equal backbone): "
                f"{_ratio_text(per_round_ratio(rounds, row, net))}   "
                f"(target <= ~1.2x; FLOP ratio {_flop_ratio(row, net)})"
            )
    return lines


def format_claims(by_key: Mapping[str, Row], rounds: Rounds) -> list[str]:
    """The U-Net KPCN's claims: its time over each reference's per round, median [min - max], how often
    the target holds, and the conv depth and width of the U-Net and both KPCN forms."""
    unet = by_key.get("unet_kpcn")
    if unet is None:
        return []
    n = len(rounds.orders)
    lines = [
        "U-Net KPCN claims (Zhu et al. 2023: >= 10x faster than KPCN, within 2x of OIDN), unet_kpcn time / "
        f"the reference's in the same round, median [min - max] over {n} rounds:"
    ]
    for key, target, what in CLAIMS:
        ref = by_key.get(key)
        ratio = per_round_ratio(rounds, unet, ref)
        if ratio is None:
            lines.append(f"  unet_kpcn / {key}: n/a ({key} {'not timed' if ref is None else ref.note})")
            continue
        spread, ratios = ratio
        met = sum(r <= target for r in ratios)
        goal = f">= {1 / target:.0f}x faster" if target < 1 else f"<= {target:g}x {key}'s time"
        inputs = ref.note.rsplit(", ", 1)[-1] if ref.depth is not None else ref.note
        faster = f" = {1 / spread.median:.3g}x faster" if target < 1 else ""
        lines.append(
            f"  unet_kpcn / {key} ({what}; {inputs}): {_ratio_text(ratio)}{faster}; "
            f"target <= {target:g}x ({goal}): met in {met}/{n} rounds"
        )
    deep = [r for r in (unet, by_key.get("kpcn"), by_key.get("kpcn_frame")) if r is not None]
    lines.append(
        "  conv layers on the longest input-to-output path (hidden channels): "
        + ", ".join(f"{r.key} {r.depth} ({r.width})" for r in deep)
    )
    return lines
