"""The `nerf` report: the per-model throughput table and its footnotes."""

from __future__ import annotations

from collections.abc import Sequence

from src.bench.nerf_timing import NerfRow
from src.bench.table import format_line

#: The row that splits Ref-NeRF's cost: the same model without its density-gradient normals.
REFNERF_WITHOUT_NORMALS = "refnerf-no-density-normals"

#: Forward-FLOP multiplier of a training step (forward + backward ~ 2 x forward) and of rendering.
TRAIN_FLOP_FACTOR, RENDER_FLOP_FACTOR = 3, 1


def train_gflops(row: NerfRow) -> float:
    return TRAIN_FLOP_FACTOR * row.flops_per_ray / row.train_seconds_per_ray / 1e9


def format_nerf_table(rows: Sequence[NerfRow]) -> str:
    """Fixed-width table; the ratios are time per ray over the first row's (so that row reads 1.00), the
    "of matmul" column the training GFLOP/s over the matmul reference row's (when there is one)."""
    first = next(r for r in rows if r.kind == "model")
    reference = next((r for r in rows if r.kind == "reference"), None)
    header = (
        "model",
        "params",
        "FLOP/ray",
        "train rays/s",
        "train ratio",
        "train GFLOP/s",
        "of matmul",
        "render rays/s",
        "render ratio",
        "render GFLOP/s",
        "note",
    )
    lines = [header]
    for r in rows:
        timed = r.kind != "reference"
        train_rate = 1 / r.train_seconds_per_ray
        render = r.render_seconds_per_ray
        first_render = first.render_seconds_per_ray
        lines.append(
            (
                r.name,
                "-" if r.params is None else f"{r.params:,}",
                f"{r.flops_per_ray:,}" if timed else "-",
                f"{train_rate:,.0f}" if timed else "-",
                f"{r.train_seconds_per_ray / first.train_seconds_per_ray:.2f}" if timed else "-",
                f"{train_gflops(r):,.2f}",
                "-" if reference is None else f"{train_gflops(r) / train_gflops(reference):.2f}",
                "-" if render is None else f"{1 / render:,.0f}",
                "-" if render is None or first_render is None else f"{render / first_render:.2f}",
                "-" if render is None else f"{RENDER_FLOP_FACTOR * r.flops_per_ray / render / 1e9:,.2f}",
                r.note,
            )
        )
    widths = [max(len(line[i]) for line in lines) for i in range(len(header))]
    return "\n".join(format_line(line, widths) for line in lines)


def _per_ray(rows: Sequence[NerfRow], name: str) -> float | None:
    return next((r.train_seconds_per_ray for r in rows if r.name == name), None)


def nerf_ratio_lines(rows: Sequence[NerfRow]) -> list[str]:
    """The issue's targets, when their rows were measured: ours vs nerf-pytorch, Ref-NeRF vs mip-NeRF."""
    lines = []
    ours, peer = _per_ray(rows, "nerf"), next((r for r in rows if r.kind == "peer"), None)
    if ours is not None and peer is not None:
        lines.append(
            f"nerf vs {peer.name}: {peer.train_seconds_per_ray / ours:.2f} x its training rays/s "
            "(same rays, settings and threads, timed alternately)"
        )
    mip, ref = _per_ray(rows, "mipnerf"), _per_ray(rows, "refnerf")
    if mip is not None and ref is not None:
        flops = {r.name: r.flops_per_ray for r in rows}
        lines.append(
            f"refnerf / mipnerf training time per ray: {ref / mip:.2f} (Ref-NeRF's density-gradient normals "
            f"and directional MLP included; MLP forward FLOP ratio {flops['refnerf'] / flops['mipnerf']:.2f} "
            "without the density gradient)"
        )
        without = _per_ray(rows, REFNERF_WITHOUT_NORMALS)
        if without is not None:
            lines.append(
                f"refnerf's density-gradient normals: {(ref - without) / mip:.2f} mip-NeRF steps per ray "
                f"(refnerf - {REFNERF_WITHOUT_NORMALS}); the rest, {without / mip:.2f}, is the model "
                "without them (its directional MLP; forward FLOP ratio "
                f"{flops[REFNERF_WITHOUT_NORMALS] / flops['mipnerf']:.2f})"
            )
    return lines


def nerf_footnotes(first: str, reference: NerfRow | None = None) -> list[str]:
    notes = [
        "FLOP/ray: MLP forward FLOPs per ray (2 x MACs of every nn.Linear, coarse + fine samples; "
        "encodings and volume rendering not counted).",
        f"ratio: the row's time per ray / {first}'s (the first model, measured in this run).",
        f"GFLOP/s: FLOP/ray x rays/s, counting a training step as {TRAIN_FLOP_FACTOR} x the forward FLOPs "
        f"(forward + backward) and rendering as {RENDER_FLOP_FACTOR} x.",
    ]
    if reference is not None:
        notes.append(
            f"{reference.name}: the machine's matmul rate, timed in the same round-robin as the training "
            "steps: y = x W^T + b, then g W and g^T x (a linear layer's input and weight gradients), "
            f"fp32, x with as many rows as the first model's step has samples; {TRAIN_FLOP_FACTOR} x "
            "2 x rows x 256^2 FLOPs. of matmul: the row's training GFLOP/s / this one's."
        )
    return notes
