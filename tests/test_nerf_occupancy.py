"""Empty-space skipping with an occupancy grid (issue 19): an all-occupied grid changes nothing, rendering
with a grid equals rendering without it where the grid is exact (the density is zero in every unoccupied
cell), the update rule's closed form, cell indexing, that the MLP really sees fewer samples, checkpoints
keep the grid, a resumed training run updates it as an uninterrupted one, and config errors."""

import subprocess

import pytest
import torch
from torch import nn

from src.errors import ConfigError
from src.models.instantiate import build_method
from src.models.nerf.inference import render_rays_chunked
from src.models.nerf.occupancy import (
    OccupancyGrid,
    cell_indices,
    cell_points,
    ema_update,
    occupancy_from_ema,
)
from src.stages import render
from src.tracking.mlflow_tracking import job_run
from src.train.checkpoint import load_checkpoint, load_weights, save_checkpoint
from src.train.nerf_trainer import NerfTrainer, train_nerf, update_occupancy
from tests.conftest import ROOT, cli_job, one_line_cli_error, one_line_error, smoke_config, stop_at
from tests.test_nerf_models import model_cfg, sphere_scene

NAMES = ("nerf", "mipnerf", "refnerf")
#: Per-ray outputs compared between renderings.
KEYS = ("rgb", "depth", "acc")

pytestmark = pytest.mark.usefixtures("single_thread")  # tests/conftest.py


def grid_args(**overrides) -> dict:
    """A grid over a box holding every sample of `sphere_scene` (camera at z = 3, t in [1, 5])."""
    args = {
        "aabb": [-4.0, -4.0, -4.0, 4.0, 4.0, 4.0],
        "resolution": 8,
        "update_every": 1,
        "decay": 0.95,
        "threshold": 0.01,
        "warmup_steps": 0,
        "sample_fraction": 0.25,
        "occupied_outside": False,
        "chunk": 1000,
    }
    return args | overrides


def grid_model(name: str, **grid) -> nn.Module:
    torch.manual_seed(0)
    return build_method(dict(model_cfg(name, "smoke"), occupancy_grid=grid_args(**grid)))


def render_both(model, rays, randomized=True):
    """Both levels of `model` on `rays` with its grid, then with the grid removed (same jitter)."""
    with_grid = model(rays, randomized=randomized, generator=torch.Generator().manual_seed(1))
    grid, model.occupancy_grid = model.occupancy_grid, None
    try:
        without = model(rays, randomized=randomized, generator=torch.Generator().manual_seed(1))
    finally:
        model.occupancy_grid = grid
    return with_grid, without


def render_keys(name: str) -> tuple[str, ...]:
    return (*KEYS, "normals", "normals_pred") if name == "refnerf" else KEYS


# --- (a) an all-occupied grid changes nothing -----------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_an_all_occupied_grid_gives_the_same_outputs_and_gradients(name):
    model = grid_model(name)
    assert bool(model.occupancy_grid.occupied.all())  # a fresh grid: every cell occupied
    rays, target = sphere_scene(n_side=6)
    with_grid, without = render_both(model, rays)
    for level_a, level_b in zip(with_grid, without, strict=True):
        for key in render_keys(name):
            assert torch.equal(level_a[key], level_b[key]), key
    grads = []
    for outputs in (with_grid, without):
        model.zero_grad()
        model.loss(outputs, target)[0].backward()
        grads.append([p.grad.clone() for p in model.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(*grads, strict=True))


# --- (b) where the grid is exact, skipping agrees with evaluating every sample --------------------------

#: The region where the test fields' density may be non-zero: cells 3-4 of 8 per axis of grid_args's box.
REGION = (-1.0, 1.0)


def _outside(points: torch.Tensor, region: tuple[float, float] = REGION) -> torch.Tensor:
    return ((points < region[0]) | (points > region[1])).any(dim=-1)


class RegionMLP(nn.Module):
    """NeRF's / mip-NeRF's MLP with density exactly 0 outside `region` (REGION unless changed); its
    encoded input carries the sample position as its last 3 features (`PositionInInput`), which the
    wrapped MLP does not see."""

    def __init__(self, inner: nn.Module) -> None:
        super().__init__()
        self.inner = inner
        self.region = REGION

    def forward(self, x_enc, view_enc):
        out = self.inner(x_enc[..., :-3], view_enc)
        return out | {"density": torch.where(_outside(x_enc[..., -3:], self.region), 0.0, out["density"])}

    def density(self, x_enc):
        return torch.where(_outside(x_enc[..., -3:], self.region), 0.0, self.inner.density(x_enc[..., :-3]))


class PositionInInput:
    """Mixin on NeRF / MipNeRF: the encoding followed by the sample position (for `RegionMLP`)."""

    def encode_positions(self, samples):
        position = samples["x"] if "x" in samples else samples["means"]
        return torch.cat([super().encode_positions(samples), position], dim=-1)


class RegionRefMLP(RegionMLP):
    """Ref-NeRF's MLP with density exactly 0 outside REGION (the positions are its IPE's `means` input)."""

    @property
    def position_encoding(self):  # what RefNeRF reads to compute the MLP's inputs
        return self.inner.position_encoding

    def forward(self, samples, viewdirs):
        out = self.inner(samples, viewdirs)
        return out | {"density": torch.where(_outside(samples["means"]), 0.0, out["density"])}

    def density(self, samples):
        return torch.where(_outside(samples["means"]), 0.0, self.inner.density(samples))


def region_model(name: str) -> nn.Module:
    """A smoke-size model whose density is zero outside REGION (softplus inside: never zero there)."""
    model = grid_model(name, threshold=0.0)
    if name == "refnerf":
        model.mlps = nn.ModuleList([RegionRefMLP(m) for m in model.mlps])
    else:
        model.__class__ = type(f"Region{type(model).__name__}", (PositionInInput, type(model)), {})
        model.mlps = nn.ModuleList([RegionMLP(m) for m in model.mlps])
        for mlp in model.mlps:  # NeRF's smoke MLP: ReLU density, zero on whole cells at random weights
            mlp.inner.density_act = nn.functional.softplus
    return model


@pytest.mark.parametrize("name", NAMES)
def test_rendering_with_an_exact_grid_equals_rendering_without_it(name):
    model = region_model(name)
    grid = model.occupancy_grid
    assert update_occupancy(model, seed=0, step=0)
    region_cells = 2**3  # REGION is 2 x 2 x 2 cells of 1 world unit
    assert int(grid.occupied.sum()) == region_cells  # threshold 0: exactly the cells of non-zero density
    rays, _ = sphere_scene(n_side=8)
    with_grid, without = render_both(model, rays)
    for level_a, level_b in zip(with_grid, without, strict=True):
        for key in render_keys(name):
            torch.testing.assert_close(level_a[key], level_b[key], rtol=0, atol=1e-5, msg=key)
    points = model.sample_inputs(rays, with_grid[0]["tdist"])[0] if name != "refnerf" else None
    if points is not None:  # the grid did skip: most coarse samples lie outside the region
        assert grid.occupied_at(points).float().mean() < 0.5
    # Evaluation (chunked, no_grad) takes the same path.
    chunked = render_rays_chunked(model, rays, chunk=20)
    grid, model.occupancy_grid = model.occupancy_grid, None
    reference = render_rays_chunked(model, rays, chunk=20)
    for key in model.render_keys:
        torch.testing.assert_close(chunked[key], reference[key], rtol=0, atol=1e-5, msg=key)


#: The coarse MLP's region in `test_the_grid_holds_the_fine_density_and_skips_both_levels`: 4 x 4 x 4 cells.
WIDE = (-2.0, 2.0)


def test_the_grid_holds_the_fine_density_and_skips_both_levels():
    """NeRF's coarse and fine MLPs differ (their own weights; here also their own regions of non-zero
    density: the coarse one on WIDE, 64 cells, the fine one on REGION, 8 cells). The grid is updated from
    the fine MLP's density (`point_density`), so it holds exactly REGION's cells, and it skips the samples
    of both levels: with it, the coarse level renders as the coarse MLP cut to REGION without a grid
    (its density between REGION and WIDE is dropped), and the fine level, resampled from those coarse
    weights, as that reference's fine level. Catches a grid built from the coarse MLP, a grid applied to
    one level only, and a level evaluated with the other level's MLP."""
    model = region_model("nerf")
    coarse, fine = model.mlps
    coarse.region = WIDE
    assert update_occupancy(model, seed=0, step=0)
    # Cell (i, j, k) spans [-4 + i, -3 + i] x ... (8 cells of 1 over [-4, 4]); occupied iff inside REGION.
    inside = [-4 + i >= REGION[0] and -3 + i <= REGION[1] for i in range(8)]
    expected = [inside[i] and inside[j] and inside[k] for i in range(8) for j in range(8) for k in range(8)]
    assert model.occupancy_grid.occupied.tolist() == expected and sum(expected) == 8
    rays, _ = sphere_scene(n_side=6)
    with torch.no_grad():
        with_grid, unmasked = render_both(model, rays)
        model.occupancy_grid, coarse.region = None, REGION
        reference = model(rays, randomized=True, generator=torch.Generator().manual_seed(1))
        x_enc = model.encode_positions({"x": torch.tensor([[0.5, -0.5, 0.25]])})
        densities = float(fine.density(x_enc)), float(coarse.density(x_enc))
    for level_a, level_b in zip(with_grid, reference, strict=True):
        for key in (*KEYS, "weights", "tdist"):
            torch.testing.assert_close(level_a[key], level_b[key], rtol=0, atol=1e-5, msg=key)
    # The fixture matters: the coarse MLP's density between REGION and WIDE shows without the grid...
    assert float((unmasked[0]["acc"] - reference[0]["acc"]).abs().max()) > 0.05
    # ...and the two MLPs differ where both are non-zero (a level on the other's MLP changes the answer).
    assert abs(densities[0] - densities[1]) > 1e-3


def test_refnerf_normals_train_through_the_gathered_samples():
    """Ref-NeRF's normals (density gradient w.r.t. the gathered means) keep their graph: the
    predicted-normal loss reaches the spatial trunk with the grid skipping samples, with the same
    gradient as without the grid (the skipped samples have zero weight)."""
    model = region_model("refnerf")
    update_occupancy(model, seed=0, step=0)
    rays, _ = sphere_scene(n_side=6)
    grads = []
    for outputs in render_both(model, rays, randomized=False):
        model.zero_grad()
        reg, _ = model.regularizers(outputs)
        reg.backward()
        grads.append(model.mlps[0].inner.trunk.layers[0].weight.grad.clone())
    assert grads[0].abs().sum() > 0
    torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-7)


# --- (c) the update rule --------------------------------------------------------------------------------


def test_ema_and_threshold_closed_form():
    ema = torch.tensor([0.0, 1.0, 2.0, 4.0])
    cells = torch.tensor([1, 3])
    new = ema_update(ema, cells, torch.tensor([0.5, 5.0]), decay=0.95)
    assert new.tolist() == pytest.approx([0.0, 0.95, 2.0, 5.0])  # max(0.95, 0.5), untouched, max(3.8, 5)
    assert ema.tolist() == [0.0, 1.0, 2.0, 4.0]  # a new tensor
    # occupied: ema > min(threshold, mean); mean 2.0
    values = torch.tensor([0.0, 0.5, 1.5, 6.0])
    assert occupancy_from_ema(values, threshold=1.0).tolist() == [False, False, True, True]
    assert occupancy_from_ema(values, threshold=10.0).tolist() == [False, False, False, True]


def test_update_follows_the_rule_step_by_step():
    """A density constant per cell (so the jitter does not matter): warm-up updates keep every cell
    occupied, later ones fold max(decay * ema, density) and threshold; other steps change nothing."""
    grid = OccupancyGrid(**grid_args(aabb=[0, 0, 0, 2, 2, 2], resolution=2, warmup_steps=2, update_every=2))
    grid.sample_fraction = 1.0  # every cell (as the warm-up)
    cell_density = torch.tensor([0.0, 0.005, 0.02, 1.0, 0.0, 0.0, 3.0, 0.5])

    def density_fn(points):
        return cell_density[cell_indices(points, grid.aabb, 2)[0]]

    gen = torch.Generator().manual_seed(0)
    assert grid.update(density_fn, 0, gen)
    assert grid.ema.tolist() == pytest.approx(cell_density.tolist()) and bool(grid.occupied.all())
    assert not grid.update(lambda p: 10 + p[:, 0], 1, gen)  # not a multiple of update_every
    assert grid.ema.tolist() == pytest.approx(cell_density.tolist())
    cell_density = torch.tensor([0.0, 0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0])
    assert grid.update(density_fn, 2, gen)
    expected = torch.tensor([0.0, 0.00475, 0.019, 2.0, 0.0, 0.0, 2.85, 0.475])
    torch.testing.assert_close(grid.ema, expected)
    assert grid.occupied.tolist() == [False, False, True, True, False, False, True, True]  # > 0.01


def test_after_the_warm_up_an_update_evaluates_a_subset_of_the_cells():
    grid = OccupancyGrid(**grid_args(resolution=8, warmup_steps=1))
    seen = []

    def density_fn(points):
        seen.append(len(points))
        return torch.ones(len(points))

    grid.update(density_fn, 0, torch.Generator().manual_seed(0))
    assert sum(seen) == 512
    seen.clear()
    grid.update(density_fn, 1, torch.Generator().manual_seed(0))  # the first update after the warm-up
    assert sum(seen) == 512
    grid.occupied[256:] = False
    seen.clear()
    grid.update(density_fn, 2, torch.Generator().manual_seed(0))
    assert 128 <= sum(seen) <= 256  # a quarter uniformly plus a quarter of the occupied ones, no repeats


def evaluated_points(grid: OccupancyGrid, step: int, seed: int) -> torch.Tensor:
    """The points one update of `grid` at `step` evaluates, with a generator seeded `seed` (the grid's
    state restored afterwards)."""
    state = {k: v.clone() for k, v in grid.state_dict().items()}
    seen = []

    def density_fn(points):
        seen.append(points)
        return torch.zeros(len(points))

    assert grid.update(density_fn, step, torch.Generator().manual_seed(seed))
    grid.load_state_dict(state)
    return torch.cat(seen)


def test_an_update_after_the_warm_up_draws_its_cells_from_the_generator():
    """The cells (uniform ones, and the occupied ones when there are more than a share) and the jitter of
    an update come from the generator it is given, not from the global RNG, so a resumed run updates as
    an uninterrupted one: the same generator seed gives the same points whatever the global RNG did in
    between, another seed other points."""
    grid = OccupancyGrid(**grid_args(resolution=8, warmup_steps=0, update_every=1))
    grid.occupied[300:] = False  # 300 occupied cells, more than the 128 drawn among them
    torch.manual_seed(0)
    first = evaluated_points(grid, 2, seed=7)
    torch.manual_seed(1)
    torch.rand(1000)
    again = evaluated_points(grid, 2, seed=7)
    other = evaluated_points(grid, 2, seed=8)
    assert 128 < len(first) <= 256 and torch.equal(first, again)
    assert len(other) != len(first) or not torch.equal(other, first)
    cells = cell_indices(first, grid.aabb, 8)[0]
    assert len(set(cells.tolist())) == len(cells)  # no repeats
    assert int(grid.occupied[cells].sum()) >= 128  # a quarter (128) drawn among the occupied ones


def test_a_share_below_one_cell_still_evaluates_one():
    """sample_fraction * cells < 1 (here 0.1 of 8): one uniformly drawn cell per update (plus as many
    occupied ones: none here), not none and not two."""
    grid = OccupancyGrid(**grid_args(resolution=2, warmup_steps=0, update_every=1, sample_fraction=0.1))
    grid.occupied.zero_()
    for seed in range(4):
        assert len(evaluated_points(grid, 1, seed)) == 1
    grid.occupied[5] = True
    points = evaluated_points(grid, 1, seed=0)
    assert len(points) in (1, 2) and 5 in cell_indices(points, grid.aabb, 2)[0].tolist()


def test_the_box_is_config_not_state():
    """The state dict holds the moving maximum and the occupancy bits only (the box comes from the config,
    so a checkpoint loads into a grid of the configured box, and keeps loading after a box change); the
    box is float32 even when the config spells it in integers."""
    grid = OccupancyGrid(**grid_args(aabb=[0, 0, 0, 2, 1, 4], resolution=4))
    assert list(grid.state_dict()) == ["ema", "occupied"]
    assert grid.aabb.dtype == torch.float32 and grid.aabb.tolist() == [0.0, 0.0, 0.0, 2.0, 1.0, 4.0]
    grid.occupied[10:] = False
    assert repr(grid) == "OccupancyGrid(resolution=4, aabb=[0.0, 0.0, 0.0, 2.0, 1.0, 4.0], occupied=0.156)"
    other = OccupancyGrid(**grid_args(aabb=[-1.25, 0, 0, 1, 1, 1.0000004], resolution=4))
    other.load_state_dict(grid.state_dict())
    assert other.aabb.tolist() == pytest.approx([-1.25, 0.0, 0.0, 1.0, 1.0, 1.0000004])
    assert "aabb=[-1.25, 0.0, 0.0, 1.0, 1.0, 1.0]" in repr(other)  # rounded to 6 decimals
    assert torch.equal(other.occupied, grid.occupied)


# --- (d) cells ------------------------------------------------------------------------------------------


def test_cell_indexing_on_a_non_cubic_box():
    aabb = torch.tensor([0.0, 0.0, 0.0, 2.0, 1.0, 4.0])
    points = torch.tensor(
        [
            [0.0, 0.0, 0.0],  # the lower corner: cell 0
            [2.0, 1.0, 4.0],  # the upper corner belongs to the last cell (3, 3, 3)
            [1.0, 0.25, 1.0],  # on inner cell boundaries: the upper cell (2, 1, 1)
            [0.49, 0.99, 3.99],  # (0, 3, 3)
            [2.0001, 0.5, 1.0],  # outside in x
            [1.0, -1e-4, 1.0],  # outside in y
        ]
    )
    flat, inside = cell_indices(points, aabb, 4)
    assert inside.tolist() == [True, True, True, True, False, False]
    assert flat[:4].tolist() == [0, 63, 2 * 16 + 1 * 4 + 1, 0 * 16 + 3 * 4 + 3]
    cells = torch.arange(64)
    for jitter in (0.0, 0.5, 0.999):
        centres = cell_points(cells, aabb, 4, torch.full((64, 3), jitter))
        assert torch.equal(cell_indices(centres, aabb, 4)[0], cells)


def test_points_outside_the_box_are_unoccupied_unless_configured():
    grid = OccupancyGrid(**grid_args(aabb=[0, 0, 0, 2, 1, 4], resolution=4))
    grid.occupied.zero_()
    grid.occupied[63] = True
    points = torch.tensor([[2.0, 1.0, 4.0], [0.1, 0.1, 0.1], [3.0, 0.5, 1.0], [-5.0, 9.0, 1.0]])
    assert grid.occupied_at(points).tolist() == [True, False, False, False]
    grid.occupied_outside = True
    assert grid.occupied_at(points).tolist() == [True, False, True, True]


# --- (e) skipping skips ---------------------------------------------------------------------------------


@pytest.mark.parametrize("name", NAMES)
def test_the_mlp_runs_only_on_occupied_samples(name):
    model = grid_model(name)
    rays, _ = sphere_scene(n_side=6)
    rows = []
    handles = [
        mlp.trunk.register_forward_pre_hook(lambda _, args: rows.append(args[0].shape[:-1].numel()))
        for mlp in model.mlps
    ]
    try:
        with torch.no_grad():
            model(rays, randomized=False)
            full = list(rows)
            rows.clear()
            model.occupancy_grid.occupied.zero_()
            model.occupancy_grid.occupied[4 * 64 : 5 * 64] = True  # the slab 0 <= x < 1
            outputs = model(rays, randomized=False)
    finally:
        for handle in handles:
            handle.remove()
    assert full == [36 * s for s in model.samples_per_level()]
    skipped = model.sample_inputs if name != "refnerf" else None
    for level, out in enumerate(outputs):
        if skipped is not None:
            expected = int(model.occupancy_grid.occupied_at(skipped(rays, out["tdist"])[0]).sum())
            assert rows[level] == expected
        assert 0 < rows[level] < full[level] / 2


def test_no_occupied_sample_renders_the_background():
    model = grid_model("mipnerf")
    model.occupancy_grid.occupied.zero_()
    rays, _ = sphere_scene(n_side=4)
    rows = []
    handle = model.mlps[0].trunk.register_forward_pre_hook(lambda _, a: rows.append(a[0].shape[:-1].numel()))
    with torch.no_grad():
        fine = model(rays, randomized=False)[-1]
    handle.remove()
    assert rows == [1, 1]  # one probe sample per level, for the outputs' shapes
    assert torch.equal(fine["acc"], torch.zeros(16)) and torch.equal(fine["rgb"], torch.ones(16, 3))


# --- (f) checkpoints and resume -------------------------------------------------------------------------


def test_a_checkpoint_keeps_the_grid(tmp_path):
    cfg = dict(model_cfg("mipnerf", "smoke"), occupancy_grid=grid_args(threshold=1e9))
    torch.manual_seed(0)
    trained = build_method(cfg)
    update_occupancy(trained, seed=0, step=0)
    assert 0 < int(trained.occupancy_grid.occupied.sum()) < 512
    state = {"model_config": cfg, "model": trained.state_dict(), "optimizer": {}}
    save_checkpoint(tmp_path / "ckpt.pt", state | {"epoch": 0, "batch_in_epoch": 1, "step": 1})
    fresh = build_method(cfg)
    assert bool(fresh.occupancy_grid.occupied.all())
    load_weights(fresh, cfg, tmp_path / "ckpt.pt")
    for key in ("ema", "occupied"):
        assert torch.equal(getattr(fresh.occupancy_grid, key), getattr(trained.occupancy_grid, key))


def test_a_model_without_grid_has_the_same_state_as_before():
    """occupancy_grid null (the default, and configs from before the option): no grid, no new state."""
    cfg = model_cfg("mipnerf", "smoke")
    assert cfg["occupancy_grid"] is None
    without_key = build_method({k: v for k, v in cfg.items() if k != "occupancy_grid"})
    model = build_method(cfg)
    assert model.occupancy_grid is None and without_key.occupancy_grid is None
    assert not any("occupancy" in key for key in model.state_dict())


@pytest.fixture(scope="module")
def nerf_data(tmp_path_factory, mitsuba_variant):
    data = tmp_path_factory.mktemp("nerf_data")
    render(smoke_config(data, data / "run", ["task=nerf"]))
    return data


def test_resume_updates_the_grid_as_an_uninterrupted_run(nerf_data, tmp_path):
    common = [
        "task=nerf",
        "model=mipnerf",
        "+occupancy_grid=on",
        "model.occupancy_grid.resolution=8",
        "model.occupancy_grid.update_every=2",
        "model.occupancy_grid.warmup_steps=4",
        "model.occupancy_grid.threshold=1e9",  # occupied: above the mean (some cells empty at once)
        "task.train.max_steps=12",
        "tracking.enabled=false",
    ]
    reference_cfg = smoke_config(nerf_data, tmp_path / "a", common)
    with job_run(reference_cfg, run_name="a", tags={}) as tracker:
        reference = NerfTrainer(reference_cfg, tracker)
        reference.fit()
    grid = reference.model.occupancy_grid
    assert 0 < int(grid.occupied.sum()) < 512
    interrupted = smoke_config(nerf_data, tmp_path / "b", common)
    with job_run(interrupted, run_name="b", tags={}) as tracker, pytest.raises(KeyboardInterrupt):
        train_nerf(interrupted, tracker, on_step=stop_at(7))
    resume = f"task.train.resume={tmp_path}/b/checkpoints"
    resumed = smoke_config(nerf_data, tmp_path / "c", [*common, resume])
    with job_run(resumed, run_name="c", tags={}) as tracker:
        summary = train_nerf(resumed, tracker)
    final = load_checkpoint(summary["checkpoint"])["model"]
    for key, value in reference.model.state_dict().items():
        assert torch.equal(final[key], value), key


# --- (g) config errors ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("key", "value"),
    [
        ("resolution", 0),
        ("resolution", 2.5),
        ("aabb", [0, 0, 0, 1, 0, 1]),  # y min == y max
        ("aabb", [0, 0, 0, 1, 1]),
        ("decay", 1.5),
        ("sample_fraction", 0.0),
        ("update_every", 0),
        ("threshold", -1.0),
        ("occupied_outside", "no"),
        ("chunk", None),  # missing
        ("resolutoin", 8),  # unknown
    ],
)
def test_bad_grid_values_are_one_line_errors_naming_the_key(key, value):
    grid = grid_args(**{key: value})
    if value is None:
        del grid[key]
    with pytest.raises(ConfigError) as excinfo:
        build_method(dict(model_cfg("mipnerf", "smoke"), occupancy_grid=grid))
    one_line_error(excinfo, f"model.occupancy_grid.{key}")
    with pytest.raises(ConfigError) as excinfo:
        build_method(dict(model_cfg("nerf", "smoke"), occupancy_grid=[8]))
    one_line_error(excinfo, "model.occupancy_grid")


def test_the_cli_exits_2_naming_the_grid_key(tmp_path):
    args = ["task=nerf", "model=mipnerf", "profile=smoke", "stage=summary", "+occupancy_grid=on"]
    bad = ["model.occupancy_grid.resolution=0", f"hydra.run.dir={tmp_path}/run"]
    cmd, env = cli_job([*args, *bad], tmp_path / "data")
    result = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    one_line_cli_error(result, "model.occupancy_grid.resolution", "expected >= 1, got 0")


# Surviving mutants of src/models/nerf/occupancy.py (bash scripts/mutation.sh occupancy), all equivalent here:
# - cell_indices `.clamp_(0, resolution - 1)` -> `.clamp_(None, resolution - 1)`: a negative cell index
#   only comes from a point below the box, which is outside and gets index 0 from the `where` (a point on
#   the lower bound gives floor(0) = 0; NaN points are outside too).
# - cell_points `torch.stack(..., dim=-1)` -> `dim=+1`: the flat cells are 1-D (P,), where 1 is -1.
# - cell_points `ijk.to(jitter.dtype)` -> `ijk.to(None)`, ema_update `density.to(ema.dtype)` -> `.to(None)`,
#   occupied_at `self.aabb.to(points.dtype)` -> `.to(None)`: `.to(None)` keeps the dtype, and type
#   promotion then gives the same values (int64 cells + float jitter; a bf16 density promotes exactly to
#   the fp32 ema's dtype, and the maximum with an fp64 one, stored back in fp32, is the same number since
#   rounding is monotonic; an fp32 box converts exactly to fp64 points, and sample positions are never
#   narrower than fp32).
# - OccupancyGrid.__init__ `persistent=False` -> `persistent=None` for the box: register_buffer treats a
#   falsy `persistent` as non-persistent (the box stays out of the state dict, test above).
