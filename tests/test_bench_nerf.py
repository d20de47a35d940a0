"""`python -m src.bench nerf`: the table of training / rendering throughput of the NeRF-family models."""

import re

import pytest

from src.bench.cli import main as bench_main
from src.bench.nerf import nerf_model_configs
from src.errors import ConfigError
from tests.conftest import one_line_error

SMOKE = ["--profile", "smoke", "--steps", "1", "--batch", "64", "--render-rays", "256", "--chunk", "128"]
COLUMNS = (
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


def _number(cell: str) -> float:
    return float(cell.replace(",", ""))


def table_rows(out: str) -> list[dict[str, str]]:
    """The table's rows as {column: cell}: from the header line to the first footnote."""
    lines = out.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("model "))
    assert re.split(r"\s{2,}", lines[start].strip()) == list(COLUMNS), lines[start]
    rows = []
    for line in lines[start + 1 :]:
        if not line.strip() or line.startswith("FLOP/ray:"):  # the ratios and footnotes follow
            break
        cells = re.split(r"\s{2,}", line.strip())
        assert len(cells) == len(COLUMNS), line
        rows.append(dict(zip(COLUMNS, cells, strict=True)))
    return rows


def model_rows(rows):
    """The timed models' rows (not nerf-pytorch's, not the matmul reference)."""
    return [r for r in rows if r["render rays/s"] != "-"]


def _check_derived_columns(rows):
    """ratio = the first row's rays/s / this row's; GFLOP/s = factor x FLOP/ray x rays/s / 1e9, with
    factor 3 for a training step (forward + backward) and 1 for rendering; within the printed rounding
    (rays/s to 1, ratio and GFLOP/s to 0.01)."""
    for phase, factor in (("train", 3), ("render", 1)):
        first = _number(rows[0][f"{phase} rays/s"])
        for r in rows:
            rate, flops = _number(r[f"{phase} rays/s"]), _number(r["FLOP/ray"])
            ratio_tol = 0.005 + first / rate * (0.5 / first + 0.5 / rate)
            assert _number(r[f"{phase} ratio"]) == pytest.approx(first / rate, abs=ratio_tol), (phase, r)
            gflops_tol = 0.005 + factor * flops * 0.5 / 1e9
            assert _number(r[f"{phase} GFLOP/s"]) == pytest.approx(
                factor * flops * rate / 1e9, abs=gflops_tol
            ), (
                phase,
                r,
            )


def test_nerf_bench_prints_one_row_per_model_relative_to_the_first(capsys):
    code = bench_main(["nerf", "--models", "nerf,mipnerf", *SMOKE])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    all_rows = table_rows(captured.out)
    rows = model_rows(all_rows)
    assert [r["model"] for r in rows] == ["nerf", "mipnerf"]
    assert all_rows[-1]["model"] == "matmul [1536,256]x[256,256]"  # 64 rays x (8 + 16) samples
    matmul = _number(all_rows[-1]["train GFLOP/s"])
    assert all_rows[-1]["of matmul"] == "1.00" and matmul > 0
    for r in rows:
        for column in ("params", "FLOP/ray", "train rays/s", "render rays/s"):
            assert _number(r[column]) > 0, (column, r)
        for column in ("train ratio", "train GFLOP/s", "render ratio", "render GFLOP/s"):
            assert _number(r[column]) >= 0, (column, r)  # 2 decimals: a load spike can round one to 0
    assert rows[0]["train ratio"] == "1.00" and rows[0]["render ratio"] == "1.00"
    _check_derived_columns(rows)
    # The smoke sizes (conf/model_profile/*_smoke.yaml), not the paper's: NeRF fine level = 8 + 8 samples.
    assert rows[0]["note"] == "8+16 samples" and rows[1]["note"] == "8+8 samples"
    for r in rows:
        assert _number(r["of matmul"]) == pytest.approx(_number(r["train GFLOP/s"]) / matmul, abs=0.01)
    assert "profile smoke" in captured.out and "3 x the forward FLOPs" in captured.out
    assert "micro-batches of 32 rays" in captured.out  # task.train.cpu_micro_batch_rays, as training
    assert "refnerf / mipnerf" not in captured.out  # Ref-NeRF not timed
    assert "[2/2] mipnerf" in captured.err  # progress, one line per model, on stderr


@pytest.mark.parametrize("bad", ["nosuchnerf", "kpcn"])  # absent, and a config that is not a NeRF
def test_nerf_bench_unknown_model_is_a_one_line_error_before_any_timing(capsys, bad):
    code = bench_main(["nerf", "--models", f"nerf,{bad}", *SMOKE])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    # One line, naming the model; nothing was timed first (no progress line for `nerf`).
    assert captured.err.count("\n") == 1 and bad in captured.err, captured.err
    with pytest.raises(ConfigError) as err:
        nerf_model_configs(f"nerf,{bad}", "smoke")
    one_line_error(err, bad, "--models", "mipnerf")


@pytest.mark.parametrize("flag", ["--chunk", "--render-rays"])
def test_nerf_bench_a_zero_size_is_a_one_line_error(capsys, flag):
    """`--chunk 0` too (its default is evaluation's chunk, so 0 must not pass as 'unset')."""
    code = bench_main(["nerf", "--models", "nerf", *SMOKE, flag, "0"])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert captured.err.count("\n") == 1 and "--chunk must be >= 1" in captured.err, captured.err


def test_benchmark_camera_is_read_from_the_nerf_dataset_config():
    """The rays' camera is the NeRF dataset's first test pose (radius, test circle, field of view, near/far
    from conf/dataset/nerf_procedural.yaml), so a change there moves the benchmark rays."""
    import math

    import torch

    from src.bench.model_configs import load_dataset_config
    from src.bench.nerf_timing import BenchCamera, benchmark_rays

    ds = load_dataset_config("nerf", "smoke")
    camera = BenchCamera.from_dataset(ds)
    assert camera == BenchCamera(4.0, 30.0, 0.0, 0.6911112070083618, 2.0, 6.0)  # the Blender scenes' setup

    def rays(cam):
        return benchmark_rays(16, torch.Generator().manual_seed(0), torch.device("cpu"), False, cam)

    base, farther = rays(camera), rays(BenchCamera.from_dataset({**ds, "radius": 5.0, "far": 7.0}))
    assert torch.norm(base["origins"][0]).item() == pytest.approx(4.0)
    assert torch.norm(farther["origins"][0]).item() == pytest.approx(5.0)
    assert farther["far"][0].item() == 7.0 and base["far"][0].item() == 6.0
    elevation = math.degrees(math.asin(base["origins"][0, 2].item() / 4.0))
    assert elevation == pytest.approx(30.0)


FAKE_RUN_NERF = """
import sys, torch
from torch import nn
import imageio, cv2  # stand-ins when absent
print("Found ckpts []")  # as create_nerf's prints: must not reach the report


def create_nerf(args):
    assert (args.N_samples, args.N_importance, args.netwidth, args.multires) == (64, 128, 256, 10)
    coarse, fine = nn.Linear(6, 3), nn.Linear(6, 3)
    print("Not ndc!")
    kwargs = {"network_fn": coarse, "network_fine": fine, "N_samples": 1, "use_viewdirs": True}
    optimizer = torch.optim.Adam([*coarse.parameters(), *fine.parameters()], lr=args.lrate)
    return kwargs, dict(kwargs), 0, None, optimizer


def render(H, W, K, chunk, rays, near, far, network_fn, network_fine, retraw, **kwargs):
    x = torch.cat([rays[0], rays[1]], dim=-1)
    return network_fine(x), None, None, {"rgb0": network_fn(x)}


def img2mse(x, y):
    return ((x - y) ** 2).mean()
"""


def test_nerf_bench_times_nerf_pytorch_from_a_directory(capsys, tmp_path):
    """--peer-nerf-pytorch DIR imports DIR/run_nerf.py (here a stand-in with its interface) and times its
    step with ours; its prints stay out of the report; the ratio line compares the two."""
    (tmp_path / "run_nerf.py").write_text(FAKE_RUN_NERF)
    (tmp_path / "run_nerf_helpers.py").write_text("")
    code = bench_main(["nerf", "--models", "nerf", *SMOKE, "--peer-nerf-pytorch", str(tmp_path)])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    rows = table_rows(captured.out)
    assert [r["model"] for r in rows][:2] == ["nerf", "nerf-pytorch"]
    peer = rows[1]
    assert peer["params"] == "42" and peer["render rays/s"] == "-"
    # time per ray over ours: the stand-in is a single Linear layer, far faster than ours, so its ratio can
    # print as 0.00 on a busy machine; checked against the two rows' rays/s (integers) instead of > 0.
    expected = _number(rows[0]["train rays/s"]) / _number(peer["train rays/s"])
    assert abs(_number(peer["train ratio"]) - expected) <= 0.005 + 0.02 * expected
    assert re.search(r"nerf vs nerf-pytorch: [0-9.]+ x its training rays/s", captured.out)
    assert "Found ckpts" not in captured.out and "Not ndc!" not in captured.out


def test_nerf_bench_peer_directory_without_nerf_pytorch_is_one_line(capsys, tmp_path):
    code = bench_main(["nerf", "--models", "nerf", *SMOKE, "--peer-nerf-pytorch", str(tmp_path)])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == ""
    assert captured.err.count("\n") == 1 and "run_nerf.py" in captured.err


def test_nerf_bench_prints_the_refnerf_over_mipnerf_ratio(capsys):
    code = bench_main(["nerf", "--models", "mipnerf,refnerf", *SMOKE, "--micro-batch", "0"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    rows = {r["model"]: r for r in table_rows(captured.out)}
    expected = _number(rows["refnerf"]["train ratio"])
    line = next(x for x in captured.out.splitlines() if x.startswith("refnerf / mipnerf"))
    assert float(line.split(": ")[1].split()[0]) == pytest.approx(expected, abs=0.01)
    assert "(whole batch, autocast none" in captured.out
    # The same Ref-NeRF without its density-gradient normals splits the ratio into their share and the rest.
    without = _number(rows["refnerf-no-density-normals"]["train ratio"])
    assert rows["refnerf-no-density-normals"]["note"].endswith("no density-gradient normals")
    assert rows["refnerf-no-density-normals"]["params"] == rows["refnerf"]["params"]
    split = next(x for x in captured.out.splitlines() if x.startswith("refnerf's density-gradient normals"))
    # Under load the share can come out below zero (timing noise): the sign is part of the number.
    normals_share, rest = (float(x) for x in re.findall(r"(-?\d+\.\d+)", split)[:2])
    assert normals_share == pytest.approx(expected - without, abs=0.02)
    assert rest == pytest.approx(without, abs=0.01)


def test_nerf_bench_autocast_times_bf16_steps_against_a_bf16_matmul(capsys):
    code = bench_main(["nerf", "--models", "mipnerf", *SMOKE, "--autocast", "bf16"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    rows = table_rows(captured.out)
    assert rows[-1]["model"] == "matmul [1024,256]x[256,256] bf16"  # 64 rays x (8 + 8) samples
    assert "autocast bf16" in captured.out.splitlines()[0]
    assert _number(rows[0]["train rays/s"]) > 0
