"""The `nerf` report: the per-model throughput table and its footnotes."""

from __future__ import annotations

from collections.abc import Sequence

from src.bench.nerf_timing import NerfRow
from src.bench.table import format_line

#: Forward-FLOP multiplier of a training step (forward + backward ~ 2 x forward) and of rendering.
TRAIN_FLOP_FACTOR, RENDER_FLOP_FACTOR = 3, 1


def format_nerf_table(rows: Sequence[NerfRow]) -> str:
    """Fixed-width table; the ratios are time per ray over the first row's (so that row reads 1.00)."""
    first = rows[0]
    header = (
        "model",
        "params",
        "FLOP/ray",
        "train rays/s",
        "train ratio",
        "train GFLOP/s",
        "render rays/s",
        "render ratio",
        "render GFLOP/s",
        "note",
    )
    lines = [header]
    for r in rows:
        train_rate, render_rate = 1 / r.train_seconds_per_ray, 1 / r.render_seconds_per_ray
        lines.append(
            (
                r.name,
                f"{r.params:,}",
                f"{r.flops_per_ray:,}",
                f"{train_rate:,.0f}",
                f"{r.train_seconds_per_ray / first.train_seconds_per_ray:.2f}",
                f"{TRAIN_FLOP_FACTOR * r.flops_per_ray * train_rate / 1e9:,.2f}",
                f"{render_rate:,.0f}",
                f"{r.render_seconds_per_ray / first.render_seconds_per_ray:.2f}",
                f"{RENDER_FLOP_FACTOR * r.flops_per_ray * render_rate / 1e9:,.2f}",
                r.note,
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join(format_line(line, widths) for line in lines)


def nerf_footnotes(first: str) -> list[str]:
    return [
        "FLOP/ray: MLP forward FLOPs per ray (2 x MACs of every nn.Linear, coarse + fine samples; "
        "encodings and volume rendering not counted).",
        f"ratio: the model's time per ray / {first}'s (the first model, measured in this run).",
        f"GFLOP/s: FLOP/ray x rays/s, counting a training step as {TRAIN_FLOP_FACTOR} x the forward FLOPs "
        f"(forward + backward) and rendering as {RENDER_FLOP_FACTOR} x.",
    ]
