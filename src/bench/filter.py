"""`python -m src.bench filter`: speed of the GP filter search's fitness evaluation (Davletaliyev 2016,
Sec. 4.1, Table 4.1: seconds per generation at 32x32 ... 512x512).

A generation-0 population (islands x population mutants of the bilateral seed, `src.gp.search`) is
evaluated on synthetic images with every feature terminal; `--sample` of its expressions are timed
(batched as the search does, `--tree-batch` per call) and the rate is extrapolated to the whole
population: expressions per second, weight evaluations per second (expressions x pixels x window offsets)
and seconds per generation (the output says when it extrapolates). Then each of `--frame-expressions`
(default: the three published ones, `src.gp.published`) filters one synthetic `--frame-width` x
`--frame-height` frame (default 1280x720, the issue's real-time target; the thesis reports < 1 s on its GPU):
seconds per frame, after one untimed warm-up on a 64x64 crop.

`--table41` compares per expression and image with the thesis instead: at each of `--resolutions`
(default Table 4.1's 32, 128, 256, 512) a generation-0 population of 4 x 50 (Sec. 4.1.2's defaults) is
sampled and timed on one synthetic square image, and `table41_rows` sets our seconds per expression and
image beside Table 4.1's seconds per iteration divided by its 200 expressions. The thesis states neither
its filter radius, nor its expressions' lengths (an expression's time grows with its feature reads, Sec.
4.1.2, Figure 4.4), nor its GPU and CPU models, so the ratios compare setups, not implementations alone.
"""

from __future__ import annotations

import argparse
import random
import time
from collections.abc import Mapping
from dataclasses import dataclass
from typing import NamedTuple

import torch

from src.bench.timing import device_name
from src.errors import ConfigError
from src.train.device import pick_device


class ThesisSeconds(NamedTuple):
    """Seconds of one search iteration in Davletaliyev 2016, Table 4.1, on its GPU and on its CPU."""

    gpu: float
    cpu: float


THESIS_TABLE41: dict[int, ThesisSeconds] = {
    32: ThesisSeconds(gpu=0.457, cpu=2.667),
    128: ThesisSeconds(gpu=6.799, cpu=734.623),
    256: ThesisSeconds(gpu=22.038, cpu=3165.72),
    512: ThesisSeconds(gpu=183.14, cpu=27501.9),
}
"""Davletaliyev 2016, Table 4.1 ("Comparison of the running time of one iteration on GPU and CPU with
different resolutions"): square resolution in pixels -> seconds of one iteration. The only copy of these
numbers in the code."""

THESIS_ISLANDS, THESIS_POPULATION = 4, 50
"""The population of every measurement in the thesis unless it says otherwise (Sec. 4.1.2: 4 islands of 50
individuals, one training image, the teapots scene), so one Table 4.1 iteration evaluates 4 x 50 = 200
expressions on one image (the thesis mentions no fitness cache, so every individual is counted)."""

THESIS_EXPRESSIONS = THESIS_ISLANDS * THESIS_POPULATION


@dataclass(frozen=True)
class Table41Row:
    """One resolution of the `--table41` table; the thesis's fields are None where Table 4.1 has no
    such resolution. Seconds are per expression and image unless named `iteration`."""

    resolution: int
    ours: float
    iteration: float  # ours x the expressions of our iteration (every individual, none deduplicated)
    thesis_gpu: float | None  # Table 4.1 GPU seconds / THESIS_EXPRESSIONS
    thesis_cpu: float | None
    ratio_gpu: float | None  # ours / thesis_gpu
    ratio_cpu: float | None


def table41_rows(measured: Mapping[int, float], expressions: int = THESIS_EXPRESSIONS) -> list[Table41Row]:
    """The rows of the `--table41` table, in `measured`'s order: `measured` maps a square resolution to
    our seconds per expression and image; `expressions` is our iteration's population (islands x
    population). The thesis's columns are always Table 4.1 / `THESIS_EXPRESSIONS` (its 4 x 50)."""
    rows = []
    for resolution, ours in measured.items():
        thesis = THESIS_TABLE41.get(resolution)
        gpu = None if thesis is None else thesis.gpu / THESIS_EXPRESSIONS
        cpu = None if thesis is None else thesis.cpu / THESIS_EXPRESSIONS
        rows.append(
            Table41Row(
                resolution=resolution,
                ours=ours,
                iteration=ours * expressions,
                thesis_gpu=gpu,
                thesis_cpu=cpu,
                ratio_gpu=None if gpu is None else ours / gpu,
                ratio_cpu=None if cpu is None else ours / cpu,
            )
        )
    return rows


def _synthetic(images: int, height: int, width: int, device: torch.device, seed: int):
    from src.gp.grammar import GRADIENT_OF, VARIABLES, VECTORS

    g = torch.Generator().manual_seed(seed)
    one = {"depth", "directIllumination", "dovGradient", "diGradient"}
    features = {}
    for name in VECTORS:
        if name == "pixel":
            continue
        channels = 1 if name in one or GRADIENT_OF.get(name) in one else 3
        features[name] = torch.rand(images, channels, height, width, generator=g).to(device)
    for name in VARIABLES:
        features[name] = (0.01 * torch.rand(images, 1, height, width, generator=g)).to(device)
    reference = torch.rand(images, 3, height, width, generator=g).to(device)
    color = (reference + 0.2 * torch.randn(images, 3, height, width, generator=g)).clamp(min=0).to(device)
    features["color"] = color
    return features, color, reference


def _timed(fn, device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    start = time.perf_counter()
    fn()
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter() - start


def frame_lines(args: argparse.Namespace, device: torch.device) -> list[str]:
    """Seconds to filter one `--frame-width` x `--frame-height` frame with each `--frame-expressions` entry
    (a published name or an expression) at `--radius`."""
    from src.gp.evaluate import filter_images
    from src.gp.published import PUBLISHED
    from src.gp.text import ExpressionError, parse

    names = [n.strip() for n in args.frame_expressions.split(";") if n.strip()]
    if not names:
        return []
    features, color, _ = _synthetic(1, args.frame_height, args.frame_width, device, args.seed)
    crop = {k: v[..., :64, :64] for k, v in features.items()}
    weights = args.frame_width * args.frame_height * (2 * args.radius + 1) ** 2
    lines = [f"  one {args.frame_width}x{args.frame_height} frame, radius {args.radius}:"]
    for name in names:
        try:
            tree = [parse(PUBLISHED.get(name, name))]
        except ExpressionError as err:
            raise ConfigError(f"--frame-expressions: {err}") from None
        filter_images(tree, crop, color[..., :64, :64], args.radius)  # warm-up
        seconds = _timed(lambda t=tree: filter_images(t, features, color, args.radius), device)
        lines.append(
            f"    {name[:60]}: {seconds:.2f} s per frame ({weights / seconds / 1e6:.1f} M weights/s)"
        )
    return lines


def _population(args: argparse.Namespace) -> tuple[list, list]:
    """Generation 0 of `args.islands` x `args.population` (the search's seeded islands: copies and
    one-mutation variants of the bilateral seed) and its distinct expressions, in order; the same for
    every image size, since building it evaluates nothing."""
    from src.gp.grammar import GRAMMAR_VECTORS, VARIABLES, VECTORS
    from src.gp.published import bilateral_expression
    from src.gp.search import GPSearch, SearchParams, search_pset
    from src.gp.variation import codebook, kernel_expressions

    def unused(trees):
        raise AssertionError("the bench times the fitness itself")

    pset = search_pset([*VECTORS, *VARIABLES])
    book = codebook(kernel_expressions(GRAMMAR_VECTORS), pset)
    params = SearchParams(islands=args.islands, population=args.population, seed=args.seed)
    seed = bilateral_expression(5.0, 0.5, 0.3, 0.1, 0.05)
    search = GPSearch(unused, seed, params, pset, book)
    random.seed(args.seed)
    population = [ind for _ in range(args.islands) for ind in search.seeded_island()]
    return population, list({str(t): t for t in population}.values())


def _time_fitness(fitness, sample: list, device: torch.device) -> float:
    """Seconds of one `fitness(sample)` after an untimed warm-up on its first two (allocator, kernels)."""
    fitness(sample[: min(2, len(sample))])
    return _timed(lambda: fitness(sample), device)


def _fmt(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.4g}"


def table41_lines(args: argparse.Namespace, device: torch.device) -> list[str]:
    """`--table41`: seconds per expression and image at each of `args.resolutions` beside Table 4.1's."""
    from src.gp.fitness import Fitness

    population, unique = _population(args)
    sample = unique[: min(args.sample, len(unique))]
    measured = {}
    for size in args.resolutions:
        features, color, reference = _synthetic(1, size, size, device, args.seed)
        fitness = Fitness(features, color, reference, args.radius, tree_batch=args.tree_batch)
        measured[size] = _time_fitness(fitness, sample, device) / len(sample)
    total = len(population)
    lengths = sum(len(t) for t in sample) / len(sample)
    batch = min(args.tree_batch, len(sample))
    lines = [
        f"GP filter fitness per expression and image vs Davletaliyev 2016, Table 4.1, on {device} "
        f"({device_name(device)}): generation 0 of {args.islands} islands x {args.population} = {total} "
        f"expressions ({len(unique)} distinct: the bilateral seed and its one-mutation variants), one "
        f"synthetic image per resolution with every feature, radius {args.radius} "
        f"({(2 * args.radius + 1) ** 2} offsets)",
        f"  timed {len(sample)} of the {len(unique)} distinct expressions at each resolution (mean length "
        f"{lengths:.1f} nodes)"
        + (", the rest extrapolated from them" if len(sample) < len(unique) else "")
        + (
            f"; {batch} per batched call, so seconds per expression are batched throughput (common "
            "sub-expressions computed once per batch)"
            if batch > 1
            else "; one expression per call"
        ),
        f"  thesis columns: Table 4.1's seconds per iteration / {THESIS_EXPRESSIONS} ({THESIS_ISLANDS} "
        f"islands x {THESIS_POPULATION} on one image, Sec. 4.1.2); its iteration also holds selection and "
        "expansion (Sec. 4.1.3: a tiny fraction of a second), ours is the fitness alone",
        f"  the thesis does not state its filter radius (ours: {args.radius}), its expressions' lengths "
        "(time grows with feature reads, Sec. 4.1.2, Figure 4.4) nor its GPU and CPU models",
        f"  ours per iteration: every one of the {total} expressions evaluated, as the thesis mentions no "
        f"fitness cache (our search evaluates the {len(unique)} distinct ones)",
        "",
        "| resolution | ours s / expression | thesis GPU s / expression | thesis CPU s / expression "
        f"| ours / thesis GPU | ours / thesis CPU | ours s / iteration of {total} |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for row in table41_rows(measured, total):
        cells = (row.ours, row.thesis_gpu, row.thesis_cpu, row.ratio_gpu, row.ratio_cpu, row.iteration)
        lines.append(f"| {row.resolution}x{row.resolution} | " + " | ".join(map(_fmt, cells)) + " |")
    frames = frame_lines(args, device)
    return [*lines, *([""] + frames if frames else [])]


def run_filter(args: argparse.Namespace) -> str:
    from src.gp.fitness import Fitness

    device = pick_device(args.device)
    if args.table41:
        return "\n".join(table41_lines(args, device))
    features, color, reference = _synthetic(args.images, args.height, args.width, device, args.seed)
    fitness = Fitness(features, color, reference, args.radius, tree_batch=args.tree_batch)
    population, unique = _population(args)
    sample = unique[: min(args.sample, len(unique))]
    seconds = _time_fitness(fitness, sample, device)
    rate = len(sample) / seconds
    weights = rate * args.images * args.width * args.height * (2 * args.radius + 1) ** 2
    total = len(population)
    extrapolated = len(sample) < len(unique)
    lengths = sum(len(t) for t in sample) / len(sample)
    thesis = THESIS_TABLE41[512]
    lines = [
        f"GP filter fitness on {device} ({device_name(device)}): {args.images} image(s) of "
        f"{args.width}x{args.height}, radius {args.radius} ({(2 * args.radius + 1) ** 2} offsets), "
        f"{args.islands} islands x {args.population} = {total} expressions ({len(unique)} distinct, "
        f"generation 0: mutants of the bilateral seed, mean length {lengths:.1f} nodes in the sample)",
        f"  timed {len(sample)} expressions in {seconds:.2f} s, {args.tree_batch} per batched call: "
        f"{rate:.3f} expression evaluations/s ({rate * args.images:.3f} expression-images/s, "
        f"{weights / 1e6:.1f} M weight evaluations/s)",
        f"  seconds per generation ({len(unique)} distinct evaluations, as the search dedupes): "
        f"{len(unique) / rate:.1f} s"
        + (f" (extrapolated from {len(sample)} of {len(unique)} distinct)" if extrapolated else ""),
        f"  thesis (Davletaliyev 2016, Table 4.1, 512x512, one iteration): {thesis.gpu} s on its GPU (CUDA), "
        f"{thesis.cpu} s on its CPU",
        *frame_lines(args, device),
    ]
    return "\n".join(lines)
