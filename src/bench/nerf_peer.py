"""`python -m src.bench nerf --peer-nerf-pytorch DIR`: nerf-pytorch's training step (Yen-Chen Lin's PyTorch
port of NeRF, github.com/yenchenlin/nerf-pytorch; not a dependency, not on PyPI) timed next to ours.

DIR is a checkout of that repository; its `run_nerf.py` is imported from there as it is (nothing of it is
copied here). The modules it imports only for data loading, plotting and progress bars (imageio, cv2,
matplotlib, tqdm, configargparse), when not installed, are replaced by empty stand-ins while it loads.
The step is its training loop's, at its lego settings (configs/lego.txt: N_rand 1024, N_samples 64,
N_importance 128, use_viewdirs, white_bkgd, perturb 1, raw_noise_std 0; netdepth/netwidth 8/256 and
multires 10/4 by default): `render` on the bench's rays on [near, far], MSE of both levels, backward, Adam.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import tempfile
import types
from collections.abc import Callable, Mapping
from contextlib import contextmanager, redirect_stdout
from pathlib import Path

import torch
from torch import nn

from src.errors import ConfigError
from src.models.nerf.summary import mlp_flops_per_sample

#: nerf-pytorch's configs/lego.txt and its defaults (run_nerf.config_parser) at which the step is timed.
LEGO = {
    "N_rand": 1024,
    "N_samples": 64,
    "N_importance": 128,
    "netdepth": 8,
    "netwidth": 256,
    "netdepth_fine": 8,
    "netwidth_fine": 256,
    "multires": 10,
    "multires_views": 4,
    "i_embed": 0,
    "use_viewdirs": True,
    "white_bkgd": True,
    "perturb": 1.0,
    "raw_noise_std": 0.0,
    "lindisp": False,
    "chunk": 1024 * 32,
    "netchunk": 1024 * 64,
    "lrate": 5e-4,
    "dataset_type": "blender",
    "no_ndc": False,
    "no_reload": True,
    "ft_path": None,
}
#: Imported by run_nerf.py for data loading, plots and progress bars only.
OPTIONAL_MODULES = ("imageio", "cv2", "matplotlib", "matplotlib.pyplot", "tqdm", "configargparse")


@contextmanager
def _stand_ins(directory: Path):
    """DIR on sys.path, and an empty module for each of `OPTIONAL_MODULES` that does not import."""
    added = []
    for name in OPTIONAL_MODULES:
        try:
            importlib.import_module(name)
        except ImportError:
            stub = types.ModuleType(name)
            stub.tqdm = stub.trange = lambda *a, **k: None  # type: ignore[attr-defined]
            sys.modules[name] = stub
            added.append(name)
    sys.path.insert(0, str(directory))
    try:
        yield
    finally:
        sys.path.remove(str(directory))
        for name in added:
            sys.modules.pop(name, None)


def load_nerf_pytorch(directory: str | Path) -> types.ModuleType:
    """nerf-pytorch's `run_nerf` module from a checkout at `directory` (a one-line ConfigError if absent)."""
    directory = Path(directory).expanduser().resolve()
    if not (directory / "run_nerf.py").is_file() or not (directory / "run_nerf_helpers.py").is_file():
        raise ConfigError(
            f"--peer-nerf-pytorch: {directory} has no run_nerf.py / run_nerf_helpers.py; expected a "
            "checkout of github.com/yenchenlin/nerf-pytorch"
        )
    with _stand_ins(directory), redirect_stdout(sys.stderr):  # its prints stay out of the report
        for name in ("run_nerf", "run_nerf_helpers"):
            sys.modules.pop(name, None)
        return importlib.import_module("run_nerf")


class NerfPytorchStep:
    """nerf-pytorch's networks and optimiser (`create_nerf`), and its training step on fixed rays."""

    def __init__(self, run_nerf: types.ModuleType, near: float, far: float, seed: int) -> None:
        self.run_nerf = run_nerf
        with tempfile.TemporaryDirectory() as basedir:  # create_nerf looks for checkpoints there
            (Path(basedir) / "bench").mkdir()
            args = argparse.Namespace(**LEGO, basedir=basedir, expname="bench")
            torch.manual_seed(seed)
            with redirect_stdout(sys.stderr):  # its progress prints stay out of the report
                train_kwargs, _, _, _, self.optimizer = run_nerf.create_nerf(args)
        self.kwargs = {**train_kwargs, "near": near, "far": far, "use_viewdirs": True}
        self.chunk = LEGO["chunk"]
        self.networks = [train_kwargs["network_fn"], train_kwargs["network_fine"]]

    def parameters(self) -> int:
        return sum(p.numel() for net in self.networks for p in net.parameters())

    def flops_per_ray(self) -> int:
        """MLP forward FLOPs per ray as `nerf_mlp_flops_per_ray` counts ours: the coarse network on
        N_samples points, the fine one on N_samples + N_importance."""
        coarse, fine = LEGO["N_samples"], LEGO["N_samples"] + LEGO["N_importance"]
        nets: list[nn.Module] = self.networks
        return coarse * mlp_flops_per_sample(nets[0]) + fine * mlp_flops_per_sample(nets[1])

    def step_fn(self, rays: Mapping[str, torch.Tensor], target: torch.Tensor) -> Callable[[], None]:
        """One iteration of run_nerf.train's core optimisation loop on `rays` (origins, directions)."""
        batch_rays = torch.stack([rays["origins"], rays["directions"]], 0)
        img2mse = self.run_nerf.img2mse
        render = self.run_nerf.render
        for net in self.networks:
            net.train()

        def step() -> None:
            rgb, _, _, extras = render(
                0, 0, None, chunk=self.chunk, rays=batch_rays, retraw=True, **self.kwargs
            )
            self.optimizer.zero_grad()
            loss = img2mse(rgb, target)
            if "rgb0" in extras:
                loss = loss + img2mse(extras["rgb0"], target)
            loss.backward()
            self.optimizer.step()

        return step
