"""Benchmarks: ``python -m src.bench denoise [--width 1280 --height 720 --rounds 7 --device auto
--models dpcn,kpcn,kpcn_frame,resnet,unet_kpcn --profile paper --log]`` and ``python -m src.bench nerf
[--models nerf,mipnerf,refnerf --profile cpu --batch 1024 --steps 5 --render-rays 4096 --chunk 4096
--device auto --micro-batch N --threads N --peer-nerf-pytorch DIR]`` and
``python -m src.bench volpath [--width 128 --height 128 --spp 16 --repeats 3 --max-depth 8 --variant auto]``
and ``python -m src.bench filter [--width 512 --height 512 --islands 4 --population 100 --radius 10
--sample 8 --device auto]`` or ``python -m src.bench filter --table41 [--resolutions 32,128,256,512
--population 50 ...]`` and ``python -m src.bench startup [--cases all --rounds 5 --warmup 1 --before DIR]``.

The command line: the subcommands' arguments and their checks; a bad argument, config value or model
name is one line on stderr and exit status 2. What each subcommand measures: `src.bench.denoise`,
`src.bench.nerf`, `src.bench.volpath`, `src.bench.filter`, `src.bench.startup`.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from hydra.errors import HydraException

from src.bench.denoise import AUTOCAST_DTYPES, CPU_TILE, MIN_ROUNDS, run_denoise
from src.bench.filter import THESIS_ISLANDS, THESIS_POPULATION, THESIS_TABLE41, run_filter
from src.bench.nerf import NERF_AUTOCAST_DTYPES, run_nerf
from src.bench.startup import run_startup
from src.bench.volpath import run_volpath
from src.errors import NrbenchError, one_line


def _check_denoise(args: argparse.Namespace) -> str | None:
    if min(args.width, args.height) < 1 or args.warmup < 0:
        return "--width and --height must be >= 1, --warmup >= 0"
    if args.rounds < MIN_ROUNDS:
        return (
            f"--rounds: expected >= {MIN_ROUNDS} (with fewer a two-sided Wilcoxon signed-rank test over "
            f"rounds cannot reach p < 0.05), found {args.rounds}"
        )
    return None


def _check_nerf(args: argparse.Namespace) -> str | None:
    if min(args.batch, args.steps, args.render_rays, 1 if args.chunk is None else args.chunk) < 1:
        return "--batch, --steps, --render-rays and --chunk must be >= 1"
    if (args.micro_batch is not None and args.micro_batch < 0) or (
        args.threads is not None and args.threads < 1
    ):
        return "--micro-batch must be >= 0, --threads >= 1"
    return None


def _check_volpath(args: argparse.Namespace) -> str | None:
    if min(args.width, args.height, args.spp, args.repeats) < 1 or args.max_depth < -1 or args.max_depth == 0:
        return "--width, --height, --spp and --repeats must be >= 1, --max-depth -1 or >= 1"
    return None


def _check_filter(args: argparse.Namespace) -> str | None:
    """Fills in the defaults that depend on `--table41` (its population and resolutions are the thesis's),
    then checks the sizes."""
    a = args
    if a.table41:
        if a.width is not None or a.height is not None:
            return "--width and --height do not apply with --table41: it times square --resolutions"
        if a.images != 1:
            return f"--images: --table41 times one image per expression, as Table 4.1; found {a.images}"
        text = ",".join(map(str, THESIS_TABLE41)) if a.resolutions is None else a.resolutions
        try:
            a.resolutions = [int(part) for part in text.split(",") if part.strip()]
        except ValueError:
            return f"--resolutions: expected comma-separated sizes in pixels such as 32,128; found {text!r}"
        if not a.resolutions or min(a.resolutions) < 1 or len(set(a.resolutions)) < len(a.resolutions):
            return f"--resolutions: expected distinct sizes >= 1 such as 32,128; found {text!r}"
    elif a.resolutions is not None:
        return "--resolutions applies only with --table41"
    a.width = 512 if a.width is None else a.width
    a.height = 512 if a.height is None else a.height
    if a.population is None:
        a.population = THESIS_POPULATION if a.table41 else 100
    sizes = (a.width, a.height, a.images, a.islands, a.population, a.sample, a.tree_batch, a.frame_width)
    if min(*sizes, a.frame_height) < 1:
        return (
            "--width, --height, --images, --islands, --population, --sample, --tree-batch, --frame-width and "
            "--frame-height must be >= 1"
        )
    if args.radius < 0:
        return "--radius must be >= 0"
    return None


def _check_startup(args: argparse.Namespace) -> str | None:
    if args.rounds < 1 or args.warmup < 0:
        return "--rounds must be >= 1, --warmup >= 0"
    return None


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m src.bench", description=__doc__.split("\n\n")[0])
    commands = parser.add_subparsers(dest="command", required=True)
    d = commands.add_parser("denoise", help="inference time of the learned denoisers, OIDN and conv2d")
    d.add_argument("--width", type=int, default=1280, help="frame width (default: the KPCN set's 1280)")
    d.add_argument("--height", type=int, default=720, help="frame height (default 720)")
    d.add_argument(
        "--rounds",
        type=int,
        default=7,
        help=f"timed rounds, each timing every model once in a rotating order (>= {MIN_ROUNDS}; default 7)",
    )
    d.add_argument(
        "--warmup", type=int, default=1, help="untimed runs of each first (allocator, cuDNN autotune)"
    )
    d.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU) | cpu | cuda | cuda:N")
    d.add_argument(
        "--models",
        default="dpcn,kpcn,kpcn_frame,resnet,unet_kpcn",
        help="comma-separated conf/model names, or kpcn_frame (the KPCN on the sequences' radiance branch)",
    )
    d.add_argument(
        "--profile", default="paper", help="profile whose model sizes are used (paper: Bako et al.)"
    )
    d.add_argument(
        "--tile", type=int, default=None, help=f"tile side; 0 = whole frame (default: CPU {CPU_TILE})"
    )
    d.add_argument("--autocast", choices=sorted(AUTOCAST_DTYPES), default="none", help="mixed precision")
    d.add_argument(
        "--tf32",
        choices=("default", "on", "off"),
        default="default",
        help="TF32 on a GPU of compute capability >= 8: default = PyTorch's flags (TF32 convolutions), on = "
        "convolutions and matmuls, off = strict fp32 (the header and the nrbench.precision tag say which)",
    )
    d.add_argument("--oidn", action=argparse.BooleanOptionalAction, default=True, help="also time OIDN")
    d.add_argument("--seed", type=int, default=0, help="seed of the random weights and inputs")
    d.add_argument(
        "--log",
        action="store_true",
        help="also log one MLflow run (experiment nrbench-bench, MLFLOW_TRACKING_URI) with bench/rounds.csv",
    )
    d.set_defaults(run=run_denoise, check=_check_denoise)

    n = commands.add_parser("nerf", help="training and rendering rays/s of NeRF, mip-NeRF and Ref-NeRF")
    n.add_argument("--models", default="nerf,mipnerf,refnerf", help="comma-separated; the first is the peer")
    n.add_argument(
        "--profile", default="cpu", help="cpu (default, as in src.run) | smoke | paper (published sizes: GPU)"
    )
    n.add_argument("--batch", type=int, default=1024, help="rays per training step")
    n.add_argument("--steps", type=int, default=5, help="timed training steps (median; after 1 untimed)")
    n.add_argument(
        "--render-rays", type=int, default=4096, help="rays rendered (1 timed pass after 1 untimed)"
    )
    n.add_argument(
        "--chunk",
        type=int,
        default=None,
        help="rays per forward pass when rendering (default: task.eval.chunk, on CPU its cpu_chunk)",
    )
    n.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU) | cpu | cuda")
    n.add_argument("--seed", type=int, default=0, help="seed of the random weights, rays and samples")
    n.add_argument(
        "--micro-batch",
        type=int,
        default=None,
        help="rays per forward + backward pass of a training step, 0 = the whole batch (default: as "
        "training does: task.train.micro_batch_rays, on CPU task.train.cpu_micro_batch_rays)",
    )
    n.add_argument("--threads", type=int, default=None, help="torch intra-op threads (default: torch's)")
    n.add_argument(
        "--autocast",
        choices=sorted(NERF_AUTOCAST_DTYPES),
        default="none",
        help="training steps and the matmul row under bf16 autocast, as task.train.amp=true (default: fp32)",
    )
    n.add_argument(
        "--peer-nerf-pytorch",
        metavar="DIR",
        default=None,
        help="also time nerf-pytorch's training step (a checkout of github.com/yenchenlin/nerf-pytorch)",
    )
    n.set_defaults(run=run_nerf, check=_check_nerf)

    v = commands.add_parser("volpath", help="samples/s of the volumetric AOV integrator vs Mitsuba's volpath")
    v.add_argument("--width", type=int, default=128, help="image width (default 128)")
    v.add_argument("--height", type=int, default=128, help="image height (default 128)")
    v.add_argument("--spp", type=int, default=16, help="samples per pixel per render (default 16)")
    v.add_argument("--repeats", type=int, default=3, help="timed renders per integrator (median reported)")
    v.add_argument("--max-depth", type=int, default=8, help="max_depth of every integrator (-1: unbounded)")
    v.add_argument("--variant", default="auto", help="auto | llvm_ad_rgb | cuda_ad_rgb")
    v.add_argument("--seed", type=int, default=0, help="seed of the first render")
    v.set_defaults(run=run_volpath, check=_check_volpath)

    f = commands.add_parser("filter", help="expression evaluations/s and s/generation of the GP search")
    f.add_argument(
        "--table41",
        action="store_true",
        help="seconds per expression and image at each of --resolutions beside Davletaliyev 2016's Table 4.1",
    )
    f.add_argument(
        "--resolutions",
        default=None,
        help="with --table41: comma-separated square sizes (default: Table 4.1's "
        + ",".join(map(str, THESIS_TABLE41))
        + ")",
    )
    f.add_argument("--width", type=int, default=None, help="image width (default: the thesis's 512)")
    f.add_argument("--height", type=int, default=None, help="image height (default 512)")
    f.add_argument("--images", type=int, default=1, help="training images per evaluation (default 1)")
    f.add_argument(
        "--islands",
        type=int,
        default=THESIS_ISLANDS,
        help=f"islands (default: the thesis's {THESIS_ISLANDS})",
    )
    f.add_argument(
        "--population",
        type=int,
        default=None,
        help=f"expressions per island (default 100; with --table41 the thesis's {THESIS_POPULATION})",
    )
    f.add_argument("--radius", type=int, default=10, help="filter radius, window (2r+1)^2 (default 10)")
    f.add_argument("--sample", type=int, default=8, help="expressions timed; the rest extrapolated")
    f.add_argument("--tree-batch", type=int, default=16, help="expressions per batched call (default 16)")
    f.add_argument("--device", default="auto", help="auto (CUDA if present, else CPU) | cpu | cuda")
    f.add_argument("--seed", type=int, default=0, help="seed of the population and the images")
    f.add_argument("--frame-width", type=int, default=1280, help="frame timed per expression (default 1280)")
    f.add_argument("--frame-height", type=int, default=720, help="(default 720)")
    f.add_argument(
        "--frame-expressions",
        default="gp_expr1;gp_expr2;gp_expr3",
        help="';'-separated published names or expressions to time on one frame ('': none)",
    )
    f.set_defaults(run=run_filter, check=_check_filter)

    s = commands.add_parser(
        "startup", help="seconds from a src.run command to its answer: the common mistakes"
    )
    s.add_argument(
        "--cases", default="all", help="comma-separated ids of src.bench.startup.CASES (default all)"
    )
    s.add_argument("--rounds", type=int, default=5, help="timed rounds, each running every command once")
    s.add_argument("--warmup", type=int, default=1, help="untimed runs of each command first (file cache)")
    s.add_argument("--before", metavar="DIR", default=None, help="also time a checkout in DIR (same rounds)")
    s.set_defaults(run=run_startup, check=_check_startup)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    problem = args.check(args)
    if problem:
        print(f"bench: {problem}", file=sys.stderr)
        return 2
    try:
        print(args.run(args))
    except (NrbenchError, HydraException) as err:  # a bad config value or an unknown model name
        print(f"bench: {one_line(err)}", file=sys.stderr)
        return 2
    return 0
